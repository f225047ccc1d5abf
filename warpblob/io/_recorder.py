"""Animated USD: one stage recording simulations, cut tet meshes, surfaces and tools frame by frame.

Per frame (time code = frame index, or ``time * fps``), each recorded item
writes time samples (OpenUSD's own TetMesh tests do the same):

- a simulation or a :class:`~warpblob.mesh.TetStructure`: a ``UsdGeom.TetMesh``
  (``points`` every frame; ``tetVertexIndices``, ``surfaceFaceVertexIndices``
  and the ``warpblob:material`` ids only on frames where the topology
  changed), and its boundary as a ``UsdGeom.Mesh`` (points every frame;
  faceVertexCounts/Indices, vertex colours and the uniform ``primvars:isCut``
  face primvar on topology changes; normals blocked: viewers compute them
  from the moving points). A simulation built on a TetMesh with a bound
  surface (:meth:`warpblob.Simulation.surface`) records that surface instead;
- a tool on a path: a ``UsdGeom.Xform`` with translate and orient ops
  sampled every frame at ``path.pose(t)``, holding the tool's mesh;
- a static :class:`~warpblob.mesh.SurfaceMesh` or :class:`~warpblob.mesh.TetMesh`:
  authored once.

Stage metadata: upAxis, metersPerUnit, timeCodesPerSecond and
framesPerSecond, start and end codes, the default prim. The stage is written
at :meth:`Recorder.close` to a temporary name and renamed (atomic).
"""

from __future__ import annotations

import pathlib

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, Vt

from .._errors import SceneError
from ..mesh._structure import TetStructure
from ..mesh._surface import SurfaceMesh
from ..mesh._tetmesh import _MATERIAL_ATTR, TetMesh
from .usd import IS_CUT_PRIMVAR, author_mesh, author_tetmesh, export_atomically, new_stage

__all__ = ["Recorder", "load_tetmesh", "load_mesh_at"]

_SUFFIXES = (".usda", ".usdc", ".usd")
#: displayColor of the tool meshes (steel grey)
TOOL_COLOR = (0.62, 0.64, 0.68)


def _prim_name(name: str) -> str:
    if not Sdf.Path.IsValidIdentifier(name):
        raise SceneError(f"Recorder: {name!r} is not a valid prim name")
    return name


class _VolumeTrack:
    """A tet mesh whose points move and whose topology may change: a simulation or a TetStructure."""

    def __init__(self, stage, base: str, source, model=None):
        self.source, self.model = source, model
        self.structure = source if isinstance(source, TetStructure) else getattr(source, "_structure", None)
        self.volume = UsdGeom.TetMesh.Define(stage, base + "/Volume")
        self.volume.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        self.points, self.extent = self.volume.CreatePointsAttr(), self.volume.CreateExtentAttr()
        self.tets_attr = self.volume.CreateTetVertexIndicesAttr()
        self.faces_attr = self.volume.CreateSurfaceFaceVertexIndicesAttr()
        self.material = self.volume.GetPrim().CreateAttribute(_MATERIAL_ATTR, Sdf.ValueTypeNames.IntArray, custom=True)
        self.surface = UsdGeom.Mesh.Define(stage, base + "/Surface")
        self.surface.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        self.surface.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        self.surface.CreateNormalsAttr().Block()
        self.s_points, self.s_extent = self.surface.CreatePointsAttr(), self.surface.CreateExtentAttr()
        self.s_counts, self.s_indices = self.surface.CreateFaceVertexCountsAttr(), self.surface.CreateFaceVertexIndicesAttr()
        self.s_color = self.surface.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
        self.s_cut = UsdGeom.PrimvarsAPI(self.surface).CreatePrimvar(
            IS_CUT_PRIMVAR, Sdf.ValueTypeNames.BoolArray, UsdGeom.Tokens.uniform
        )
        self.version = None
        self.surface_nodes = None
        self.topology_codes: list[float] = []

    def _positions(self) -> np.ndarray:
        if isinstance(self.source, TetStructure):
            return np.asarray(self.source.node_position, dtype=np.float32)
        return np.asarray(self.source.positions, dtype=np.float32)

    def write(self, code: float) -> None:
        x = self._positions()
        version = self.structure.topology_version if self.structure is not None else 0
        if version != self.version:
            self._topology(code)
            self.version = version
        points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(x))
        self.points.Set(points, code)
        self.extent.Set(UsdGeom.PointBased.ComputeExtent(points), code)
        if self.surface_nodes is not None:
            sp = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(x[self.surface_nodes]))
        else:  # an embedded surface of a TetMesh simulation
            sp = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(self.source.surface_positions(), dtype=np.float32))
        self.s_points.Set(sp, code)
        self.s_extent.Set(UsdGeom.PointBased.ComputeExtent(sp), code)

    def _topology(self, code: float) -> None:
        self.topology_codes.append(code)
        if self.structure is not None:
            s = self.structure
            alive = np.asarray(s.cell_alive)
            tets = np.ascontiguousarray(np.asarray(s.cell_nodes)[alive], dtype=np.int32)
            material = np.asarray(s.cell_material)[alive]
            surf = s.surface(model=self.model if self.model is not None else getattr(self.source, "model", None))
            nodes = surf.stats["nodes"]
            faces_global = nodes[surf.faces]
            self.surface_nodes = nodes
            faces, colors, is_cut = surf.faces, surf.colors, surf.is_cut
        else:
            e = self.source.elements
            alive = e.alive_host
            tets = np.ascontiguousarray(e.tets_host[alive], dtype=np.int32)
            material = np.zeros(len(tets), dtype=np.int32)
            faces_global = TetMesh._trusted(e.rest_host, tets, None, {}).surface_faces()
            emb = self.source.embedding
            if emb is None:
                raise SceneError("Recorder: a simulation built on a TetMesh needs a bound surface (sim.surface(mesh))")
            faces, colors, is_cut = emb.mesh.faces, emb.mesh.colors, np.zeros(emb.mesh.face_count, dtype=bool)
        self.tets_attr.Set(Vt.Vec4iArray.FromNumpy(tets), code)
        self.faces_attr.Set(Vt.Vec3iArray.FromNumpy(np.ascontiguousarray(faces_global, dtype=np.int32)), code)
        self.material.Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(material, dtype=np.int32)), code)
        self.s_counts.Set(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)), code)
        self.s_indices.Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, dtype=np.int32).ravel()), code)
        self.s_color.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(colors, dtype=np.float32)), code)
        self.s_cut.Set(Vt.BoolArray.FromNumpy(np.ascontiguousarray(is_cut, dtype=bool)), code)


class _ToolTrack:
    """A rigid tool on a path: an Xform sampled per frame holding the tool's mesh."""

    def __init__(self, stage, base: str, tool, path):
        self.tool, self.path = tool, path
        xform = UsdGeom.Xform.Define(stage, base)
        self.translate = xform.AddTranslateOp()
        self.orient = xform.AddOrientOp()
        mesh = UsdGeom.Mesh.Define(stage, base + "/Mesh")
        v = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(tool.vertices, dtype=np.float32))
        mesh.CreatePointsAttr(v)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(tool.faces), 3, dtype=np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(tool.faces, np.int32).ravel()))
        mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(v))
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([Gf.Vec3f(*TOOL_COLOR)]))

    def write(self, code: float, time: float) -> None:
        pose = self.path.pose(time)
        self.translate.Set(Gf.Vec3d(*map(float, pose.position)), code)
        x, y, z, w = map(float, pose.rotation)
        self.orient.Set(Gf.Quatf(w, x, y, z), code)


class Recorder:
    """Record simulations, cut meshes and tools into one animated USD stage.

    Args:
        path: ``.usda``/``.usdc``/``.usd`` target (written by :meth:`close`, atomically).
        fps: time codes (and frames) per second.
        up_axis: "Z" (the model's frame) or "Y".
        meters_per_unit: stage metres per model unit (1 for a simulation in SI units).
        root: the default prim's name.

    Example:
        >>> import os, tempfile
        >>> import warpblob as wb
        >>> import warpblob.usd
        >>> s = wb.TetStructure.from_tetmesh(wb.mesh.box_tetmesh((0, 0, 0), (1, 1, 1), (2, 2, 2)))
        >>> rec = Recorder(os.path.join(tempfile.mkdtemp(), "cut.usda"))
        >>> _ = rec.add(s, name="Box")
        >>> rec.frame()
        >>> _ = wb.cut.cut(s, wb.cut.SweepSurface.plane((0.4, 0.5, 0.5), (1, 0.2, 0), 2.0))
        >>> rec.frame()
        >>> rec.close().suffix, load_tetmesh(rec.path, time=1).tet_count > 48
        ('.usda', True)
    """

    def __init__(self, path, *, fps: float = 60.0, up_axis: str = "Z", meters_per_unit: float = 1.0,
                 root: str = "World"):  # fmt: skip
        self.path = pathlib.Path(path)
        if self.path.suffix not in _SUFFIXES:
            raise SceneError(f"Recorder: path must end in one of {', '.join(_SUFFIXES)}, got {str(path)!r}")
        if not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
            raise SceneError(f"Recorder: fps must be a positive number, got {fps!r}")
        if up_axis not in ("Z", "Y"):
            raise SceneError(f"Recorder: up_axis must be 'Z' or 'Y', got {up_axis!r}")
        if not (isinstance(meters_per_unit, (int, float)) and meters_per_unit > 0):
            raise SceneError(f"Recorder: meters_per_unit must be a positive number, got {meters_per_unit!r}")
        self.fps = float(fps)
        self.root = "/" + _prim_name(root)
        self.stage = new_stage(meters_per_unit=meters_per_unit, default_prim=root, start=0, end=0, fps=self.fps)
        if up_axis == "Y":
            UsdGeom.SetStageUpAxis(self.stage, UsdGeom.Tokens.y)
        self._tracks: list = []
        self._names: set[str] = set()
        self.frame_count = 0
        self.codes: list[float] = []
        self._closed = False

    def _name(self, name: str | None, default: str) -> str:
        name = _prim_name(name or default)
        base, k = name, 1
        while name in self._names:
            k += 1
            name = f"{base}{k}"
        self._names.add(name)
        return f"{self.root}/{name}"

    def add(self, item, path=None, *, name: str | None = None, model=None) -> str:
        """Record ``item`` from the next frame on; returns its prim path.

        Args:
            item: a :class:`~warpblob.Simulation` (its volume, surface and tools),
                a :class:`~warpblob.mesh.TetStructure`, a tool (with ``path``), or a
                static :class:`~warpblob.mesh.SurfaceMesh` / :class:`~warpblob.mesh.TetMesh`.
            path: the tool's :class:`~warpblob.tools.Path` (tools only).
            name: prim name (default by kind; made unique).
            model: BlobTree model whose colour field colours a cut surface (default: the simulation's).
        """
        from ..sim import Simulation
        from ..tools import Tool

        if self._closed:
            raise SceneError("Recorder.add: the recorder is closed")
        if isinstance(item, (Simulation, TetStructure)):
            base = self._name(name, "Simulation" if isinstance(item, Simulation) else "Volume")
            UsdGeom.Xform.Define(self.stage, base)
            self._tracks.append(_VolumeTrack(self.stage, base, item, model))
            if isinstance(item, Simulation):
                for k, record in enumerate((*item.tools, *item.cutters)):
                    self._tracks.append(_ToolTrack(self.stage, f"{base}/Tool{k}", record.tool, record.path))
            return base
        if isinstance(item, Tool):
            if path is None:
                raise SceneError("Recorder.add: a tool needs its path")
            base = self._name(name, "Tool")
            self._tracks.append(_ToolTrack(self.stage, base, item, path))
            return base
        if isinstance(item, SurfaceMesh):
            base = self._name(name, "Surface")
            author_mesh(self.stage, base, item)
            return base
        if isinstance(item, TetMesh):
            base = self._name(name, "TetMesh")
            author_tetmesh(self.stage, base, item)
            return base
        raise SceneError(f"Recorder.add: cannot record a {type(item).__name__}")

    def frame(self, time: float | None = None) -> None:
        """Write every recorded item's state now; ``time`` in seconds (default: the frame index / fps)."""
        if self._closed:
            raise SceneError("Recorder.frame: the recorder is closed")
        t = self.frame_count / self.fps if time is None else float(time)
        code = float(self.frame_count) if time is None else round(t * self.fps, 6)
        if self.codes and code <= self.codes[-1]:
            raise SceneError(f"Recorder.frame: time {t!r} s is not after the last frame's")
        for track in self._tracks:
            if isinstance(track, _ToolTrack):
                track.write(code, t)
            else:
                track.write(code)
        self.codes.append(code)
        self.frame_count += 1

    def close(self) -> pathlib.Path:
        """Set the time range and write the stage (atomically); returns its path."""
        if not self._closed:
            if self.codes:
                self.stage.SetStartTimeCode(self.codes[0])
                self.stage.SetEndTimeCode(self.codes[-1])
            export_atomically(self.stage.GetRootLayer(), self.path, "Recorder.close")
            self._closed = True
        return self.path

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is None:
            self.close()


def _stage(path):
    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise SceneError(f"cannot open USD stage {str(path)!r}")
    return stage


def _find(stage, schema, prim_path):
    if prim_path is not None:
        prim = stage.GetPrimAtPath(prim_path)
        if not prim or not prim.IsA(schema):
            raise SceneError(f"no {schema.__name__} at {prim_path!r}")
        return prim
    for prim in stage.Traverse():
        if prim.IsA(schema):
            return prim
    raise SceneError(f"the stage has no {schema.__name__}")


def _prim_at(path, schema, prim_path, time):
    """(stage, prim, time code) of the first ``schema`` prim of the stage at ``path`` (or ``prim_path``)."""
    stage = _stage(path)
    return stage, _find(stage, schema, prim_path), Usd.TimeCode(time) if not isinstance(time, Usd.TimeCode) else time


def load_tetmesh(path, *, time: float = Usd.TimeCode.Default(), prim_path: str | None = None) -> TetMesh:
    """The :class:`~warpblob.mesh.TetMesh` of a recorded stage at time code ``time`` (first TetMesh by default)."""
    stage, prim, code = _prim_at(path, UsdGeom.TetMesh, prim_path, time)  # the stage held: prims die with it
    geom = UsdGeom.TetMesh(prim)
    nodes = np.asarray(geom.GetPointsAttr().Get(code), dtype=np.float32).reshape(-1, 3)
    tets = np.asarray(geom.GetTetVertexIndicesAttr().Get(code), dtype=np.int32).reshape(-1, 4)
    attr = prim.GetAttribute(_MATERIAL_ATTR)
    material = np.asarray(attr.Get(code), dtype=np.int32) if attr and attr.Get(code) is not None else None
    used, inverse = np.unique(tets, return_inverse=True)
    return TetMesh(nodes[used], inverse.reshape(-1, 4), material)


def load_mesh_at(path, *, time: float = Usd.TimeCode.Default(), prim_path: str | None = None) -> SurfaceMesh:
    """The :class:`~warpblob.mesh.SurfaceMesh` of a recorded stage at ``time`` (``is_cut`` from its primvar)."""
    stage, prim, code = _prim_at(path, UsdGeom.Mesh, prim_path, time)
    geom = UsdGeom.Mesh(prim)
    v = np.asarray(geom.GetPointsAttr().Get(code), dtype=np.float32).reshape(-1, 3)
    f = np.asarray(geom.GetFaceVertexIndicesAttr().Get(code), dtype=np.int32).reshape(-1, 3)
    pv = UsdGeom.PrimvarsAPI(geom)
    color = pv.GetPrimvar("displayColor").Get(code) if pv.HasPrimvar("displayColor") else None
    colors = np.asarray(color, dtype=np.float32) if color is not None and len(color) == len(v) else np.full_like(v, 0.8)
    cut = pv.GetPrimvar(IS_CUT_PRIMVAR).Get(code) if pv.HasPrimvar(IS_CUT_PRIMVAR) else None
    n = np.zeros_like(v)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    for j in range(3):
        np.add.at(n, f[:, j], fn)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
    return SurfaceMesh(v, f, n, colors, is_cut=None if cut is None else np.asarray(cut, dtype=bool))
