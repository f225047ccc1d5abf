"""Animated USD: one stage recording simulations, cut tet meshes, surfaces and tools frame by frame.

Per frame (time code = frame index, or ``time * fps``), each recorded item
writes time samples (OpenUSD's own TetMesh tests do the same):

- a simulation or a :class:`~warpblob.mesh.TetStructure`, at ``<base>``:

  - ``<base>/Volume``, a ``UsdGeom.TetMesh`` of every live tet: ``points``
    every frame; ``tetVertexIndices``, ``surfaceFaceVertexIndices`` and the
    per-tet uniform int primvar ``primvars:materialId`` only on frames where
    the topology changed (:attr:`~warpblob.mesh.TetStructure.topology_version`).
    Its purpose is ``guide``: it is the simulation's data, and viewers draw
    the surfaces below instead of the same triangles twice;
  - ``<base>/Pieces/Piece<k>``, one ``Xform`` per separated piece
    (:meth:`~warpblob.mesh.TetStructure.components`), from the frame it
    appears: ``visibility`` is ``invisible`` before that frame and after the
    piece is gone. A piece keeps its prim across cuts: a new piece takes
    the prim of the old one it shares the most nodes with (by rest position,
    which survives renumbering), the others get new prims. Each piece holds
    one ``UsdGeom.Mesh`` per material id, ``M<id>``, the boundary faces of
    its tets of that material (points every frame; faceVertexCounts/Indices,
    vertex ``displayColor``, the uniform ``primvars:isCut`` face primvar and
    the vertex int primvar ``primvars:warpblob:node``, the structure node of
    each vertex, on topology changes; normals blocked: viewers compute them
    from the moving points), bound to ``/<root>/Looks/Material<id>``;
  - a simulation built on a :class:`~warpblob.mesh.TetMesh` with a bound
    surface (:meth:`warpblob.Simulation.surface`) records that surface as
    ``<base>/Surface`` instead (its displayColor sampled per frame, the
    contact area highlighted, when the simulation has tools);
  - the simulation's tools and cutters at ``<base>/Tools/Tool<k>``;

- a tool on a path: a ``UsdGeom.Xform`` with translate and orient ops
  (double precision) sampled every frame at ``path.pose(t)``, holding the
  tool's mesh, its ``visibility`` ``invisible`` while the time is more than
  :data:`TOOL_PARK` seconds before its path starts or after it ends (sampled
  where it changes);
- a static :class:`~warpblob.mesh.SurfaceMesh` or :class:`~warpblob.mesh.TetMesh`:
  authored once.

Materials: one ``UsdShade.Material`` per material id (a
``UsdPreviewSurface`` whose ``diffuseColor`` is the tissue's colour), bound
per prim, not through GeomSubsets: one material per Mesh is what every
viewer draws, and a GeomSubset's face indices cannot follow a topology that
changes in Blender's importer. The tissue colour is the ``material_colors``
given to :meth:`Recorder.add` (its meshes' displayColor then that colour
too: a layered mesh recorded with one model's colour field shows its
layers), else the mean of the model's colour field over that material's
boundary vertices when the material first shows, else a fixed palette.

Stage metadata: upAxis, metersPerUnit, timeCodesPerSecond and
framesPerSecond, start and end codes, the default prim.

Streaming: a ``.usdc`` (or ``.usd``) recording is a crate layer created
under a temporary name beside the target; every ``flush_bytes`` of authored
arrays it is saved. A crate layer's ``Save`` appends the new values to the
file and keeps only their file offsets in memory, so memory stays bounded
whatever the number of frames (measured in ``tests/test_recorder.py`` and
``docs/usd.md``). :meth:`Recorder.close` saves once more and renames the file
into place (atomic). A ``.usda`` recording is text, which cannot be
appended to: it is held in memory and exported at close.
"""

from __future__ import annotations

import os
import pathlib
import secrets

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, Vt

from .._errors import SceneError
from ..mesh._structure import TetStructure
from ..mesh._surface import SurfaceMesh
from ..mesh._tetmesh import TetMesh
from .usd import IS_CUT_PRIMVAR, MATERIAL_ATTR, author_mesh, author_tetmesh, check_target, export_atomically, new_stage

__all__ = ["Recorder", "load_tetmesh_at", "load_mesh_at", "MATERIAL_PRIMVAR", "NODE_PRIMVAR"]

_SUFFIXES = (".usda", ".usdc", ".usd")
#: displayColor of the tool meshes (steel grey)
TOOL_COLOR = (0.62, 0.64, 0.68)
#: seconds a tool stays visible before its path starts and after it ends (a finished stroke's scalpel goes)
TOOL_PARK = 0.1
#: uniform int primvar: the material id of each tet (on a TetMesh), constant on a piece's per-material Mesh
MATERIAL_PRIMVAR = "materialId"
#: vertex int primvar of a piece's Mesh: the structure node of each vertex (pieces' meshes join on it)
NODE_PRIMVAR = "warpblob:node"
#: fallback tissue colours (material id modulo its length) when neither colours nor a model are given
_PALETTE = np.array([[0.85, 0.62, 0.55], [0.55, 0.7, 0.85], [0.9, 0.8, 0.45], [0.6, 0.8, 0.55],
                     [0.8, 0.55, 0.8], [0.55, 0.8, 0.8], [0.95, 0.65, 0.35], [0.7, 0.7, 0.7]], np.float32)  # fmt: skip
#: default bytes of array data authored between two saves of a streamed (crate) recording
FLUSH_BYTES = 32 << 20


def _prim_name(name: str) -> str:
    if not Sdf.Path.IsValidIdentifier(name):
        raise SceneError(f"Recorder: {name!r} is not a valid prim name")
    return name


def _vec3f(a) -> Vt.Vec3fArray:
    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a, dtype=np.float32).reshape(-1, 3))


def _ints(a) -> Vt.IntArray:
    return Vt.IntArray.FromNumpy(np.ascontiguousarray(a, dtype=np.int32).ravel())


def _rest_keys(rest: np.ndarray) -> np.ndarray:
    """(N,) int64 hash of float32 rest positions (bit patterns): node identity that survives renumbering."""
    bits = np.ascontiguousarray(rest, dtype=np.float32).view(np.uint32).astype(np.uint64)
    k = bits[:, 0] * np.uint64(0x9E3779B97F4A7C15)
    k ^= bits[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F) + (k >> np.uint64(29))
    k ^= bits[:, 2] * np.uint64(0x165667B19E3779F9) + (k >> np.uint64(31))
    return k.view(np.int64)


class _Looks:
    """``/<root>/Looks/Material<id>``: one UsdPreviewSurface material per tissue, made when first used."""

    def __init__(self, rec):
        self.rec = rec
        self.materials: dict = {}

    def get(self, key, color) -> UsdShade.Material:
        if key not in self.materials:
            stage = self.rec.stage
            name = f"Material{key}" if isinstance(key, (int, np.integer)) else str(key)
            path = f"{self.rec.root}/Looks/{name}"
            UsdGeom.Scope.Define(stage, f"{self.rec.root}/Looks")
            material = UsdShade.Material.Define(stage, path)
            shader = UsdShade.Shader.Define(stage, path + "/PreviewSurface")
            shader.CreateIdAttr("UsdPreviewSurface")
            shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*map(float, color)))
            shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
            material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
            self.materials[key] = material
        return self.materials[key]

    def bind(self, prim, key, color) -> None:
        material = self.get(key, color)
        UsdShade.MaterialBindingAPI.Apply(prim).Bind(material)


class _PieceMesh:
    """One material's boundary faces of one piece: a Mesh whose topology is re-authored on changes."""

    def __init__(self, stage, path: str):
        self.mesh = UsdGeom.Mesh.Define(stage, path)
        self.mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        self.mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        self.mesh.CreateNormalsAttr().Block()
        self.points, self.extent = self.mesh.CreatePointsAttr(), self.mesh.CreateExtentAttr()
        self.counts, self.indices = self.mesh.CreateFaceVertexCountsAttr(), self.mesh.CreateFaceVertexIndicesAttr()
        api = UsdGeom.PrimvarsAPI(self.mesh)
        self.color = self.mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
        self.cut = api.CreatePrimvar(IS_CUT_PRIMVAR, Sdf.ValueTypeNames.BoolArray, UsdGeom.Tokens.uniform)
        self.node = api.CreatePrimvar(NODE_PRIMVAR, Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex)
        self.material = api.CreatePrimvar(MATERIAL_PRIMVAR, Sdf.ValueTypeNames.Int, UsdGeom.Tokens.constant)
        self.nodes: np.ndarray | None = None  # structure node of each vertex; None: absent now
        self.visible = None

    def topology(self, code, nodes, faces, colors, is_cut) -> int:
        self.nodes = nodes
        self.counts.Set(_ints(np.full(len(faces), 3)), code)
        self.indices.Set(_ints(faces), code)
        self.color.Set(_vec3f(colors), code)
        self.cut.Set(Vt.BoolArray.FromNumpy(np.ascontiguousarray(is_cut, dtype=bool)), code)
        self.node.Set(_ints(nodes), code)
        return 16 * len(faces) + 16 * len(nodes)


class _Piece:
    """A separated piece: an Xform with one Mesh per material id, visible while the piece exists."""

    def __init__(self, track, index: int):
        self.track, self.path = track, f"{track.base}/Pieces/Piece{index}"
        self.xform = UsdGeom.Xform.Define(track.rec.stage, self.path)
        self.meshes: dict[int, _PieceMesh] = {}
        self.keys = np.zeros(0, dtype=np.int64)
        self.alive = True
        self.visible = None


def _set_visible(imageable, holder, visible: bool, code, first_code) -> None:
    """Author ``visibility`` where it changes; a prim first shown after the first frame is invisible before."""
    if holder.visible == visible:
        return
    attr = imageable.GetVisibilityAttr()
    token = UsdGeom.Tokens.inherited if visible else UsdGeom.Tokens.invisible
    if holder.visible is None:  # a new prim
        if code != first_code:
            attr.Set(UsdGeom.Tokens.invisible, first_code)
            attr.Set(token, code)
    else:
        if attr.GetNumTimeSamples() == 0 and code != first_code:  # held values: the state before needs a sample
            attr.Set(UsdGeom.Tokens.inherited if holder.visible else UsdGeom.Tokens.invisible, first_code)
        attr.Set(token, code)
    holder.visible = visible


class _VolumeTrack:
    """A tet mesh whose points move and whose topology may change: a simulation or a TetStructure."""

    def __init__(self, rec, base: str, source, model=None, material_colors=None):
        self.rec, self.base, self.source = rec, base, source
        stage = rec.stage
        self.structure = source if isinstance(source, TetStructure) else getattr(source, "_structure", None)
        self.model = model if model is not None else getattr(source, "model", None)
        self.colors = {} if material_colors is None else _color_table(material_colors)
        self.given = set(self.colors)  # tissues whose colour was given: their meshes are drawn in it
        self.volume = UsdGeom.TetMesh.Define(stage, base + "/Volume")
        self.volume.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        self.points, self.extent = self.volume.CreatePointsAttr(), self.volume.CreateExtentAttr()
        self.tets_attr = self.volume.CreateTetVertexIndicesAttr()
        self.faces_attr = self.volume.CreateSurfaceFaceVertexIndicesAttr()
        self.material = UsdGeom.PrimvarsAPI(self.volume).CreatePrimvar(
            MATERIAL_PRIMVAR, Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.uniform
        )
        self.version = None
        self.topology_codes: list[float] = []
        self.pieces: list[_Piece] = []
        self.surface = None  # the embedded surface of a TetMesh simulation
        self.shade = False
        emb = getattr(source, "embedding", None) if self.structure is None else None
        if self.structure is not None or emb is not None:  # surfaces are drawn: the volume is a guide
            self.volume.CreatePurposeAttr(UsdGeom.Tokens.guide)
        if emb is not None:
            self.surface = author_mesh(stage, base + "/Surface", emb.mesh)
            self.surface.GetNormalsAttr().Block()
            self.shade = bool(getattr(source, "tools", ()))
            self.s_points, self.s_extent = self.surface.GetPointsAttr(), self.surface.GetExtentAttr()
        elif self.structure is not None:
            UsdGeom.Scope.Define(stage, base + "/Pieces")

    def _positions(self) -> np.ndarray:
        if isinstance(self.source, TetStructure):
            return np.asarray(self.source.node_position, dtype=np.float32)
        return np.asarray(self.source.positions, dtype=np.float32)

    def write(self, code: float) -> int:
        """Author this frame; returns the bytes of array data written."""
        x = self._positions()
        version = self.structure.topology_version if self.structure is not None else 0
        written = 0
        if version != self.version:
            written += self._topology(code, x)
            self.version = version
        points = _vec3f(x)
        self.points.Set(points, code)
        self.extent.Set(UsdGeom.PointBased.ComputeExtent(points), code)
        written += 12 * len(x)
        if self.surface is not None:
            sp = _vec3f(self.source.surface_positions())
            self.s_points.Set(sp, code)
            self.s_extent.Set(UsdGeom.PointBased.ComputeExtent(sp), code)
            written += 12 * len(sp)
            if self.shade:
                from ..sim._contact import highlight

                mesh = self.source.embedding.mesh
                colors = highlight(mesh.colors, self.source.surface_contact())
                self.surface.GetDisplayColorPrimvar().Set(_vec3f(colors), code)
                written += 12 * len(colors)
            return written
        for piece in self.pieces:
            for part in piece.meshes.values():
                if part.nodes is not None:
                    p = _vec3f(x[part.nodes])
                    part.points.Set(p, code)
                    part.extent.Set(UsdGeom.PointBased.ComputeExtent(p), code)
                    written += 12 * len(part.nodes)
        return written

    def _topology(self, code: float, x: np.ndarray) -> int:
        self.topology_codes.append(code)
        if self.structure is None:
            e = self.source.elements
            tets = np.ascontiguousarray(e.tets_host[e.alive_host], dtype=np.int32)
            material = np.zeros(len(tets), dtype=np.int32)
            faces = TetMesh._trusted(e.rest_host, tets, None, {}).surface_faces()
        else:
            return self._structure_topology(code)
        self.tets_attr.Set(Vt.Vec4iArray.FromNumpy(tets), code)
        self.faces_attr.Set(Vt.Vec3iArray.FromNumpy(np.ascontiguousarray(faces, dtype=np.int32)), code)
        self.material.Set(_ints(material), code)
        return 20 * len(tets) + 12 * len(faces)

    def _structure_topology(self, code: float) -> int:
        s = self.structure
        alive = np.asarray(s.cell_alive)
        cell_nodes = np.asarray(s.cell_nodes)
        cell_material = np.asarray(s.cell_material)
        tets = np.ascontiguousarray(cell_nodes[alive], dtype=np.int32)
        surf = s.surface(model=self.model)
        nodes = np.asarray(surf.stats["nodes"])
        faces_global = nodes[surf.faces]
        # the cell of each boundary face, in surface()'s order (its faces are the live outer faces, ascending)
        fc = np.asarray(s.face_cells)
        outer = np.flatnonzero(np.asarray(s.face_alive) & (fc[:, 0] >= 0) & (fc[:, 1] < 0))
        face_cell = fc[outer, 0]
        if len(face_cell) != len(faces_global):
            raise SceneError("Recorder: the structure's boundary changed while it was read")
        self.tets_attr.Set(Vt.Vec4iArray.FromNumpy(tets), code)
        self.faces_attr.Set(Vt.Vec3iArray.FromNumpy(np.ascontiguousarray(faces_global, dtype=np.int32)), code)
        self.material.Set(_ints(cell_material[alive]), code)
        written = 20 * len(tets) + 12 * len(faces_global)
        # node colours of the whole boundary, looked up by structure node
        color_of = np.zeros((len(s.node_rest), 3), dtype=np.float32)
        color_of[nodes] = surf.colors
        labels = s.components()
        pieces = self._match(labels, cell_nodes, alive)
        face_piece = labels[face_cell]
        face_material = cell_material[face_cell]
        first = self.rec.codes[0] if self.rec.codes else code
        order = np.lexsort((face_material, face_piece))
        fp, fm = face_piece[order], face_material[order]
        starts = np.flatnonzero(np.r_[True, (fp[1:] != fp[:-1]) | (fm[1:] != fm[:-1])])
        ends = np.r_[starts[1:], len(order)]
        present: dict[int, dict[int, np.ndarray]] = {}
        for a, b in zip(starts.tolist(), ends.tolist()):
            present.setdefault(int(fp[a]), {})[int(fm[a])] = order[a:b]
        for label, piece in enumerate(pieces):
            # a new piece's meshes are shown and hidden with it
            part_first = code if piece.visible is None else first
            _set_visible(piece.xform, piece, True, code, first)
            for m, rows in sorted(present.get(label, {}).items()):
                part = piece.meshes.get(m)
                if part is None:
                    part = piece.meshes[m] = _PieceMesh(self.rec.stage, f"{piece.path}/M{m}")
                    part.material.Set(m)
                    color = self._tissue_color(m, color_of, faces_global[rows])
                    self.rec.looks.bind(part.mesh.GetPrim(), m, color)
                used, local = np.unique(faces_global[rows], return_inverse=True)
                shade = np.tile(self.colors[m], (len(used), 1)) if m in self.given else color_of[used]
                written += part.topology(code, used.astype(np.int32), local.reshape(-1, 3), shade,
                                         surf.is_cut[rows])  # fmt: skip
                _set_visible(part.mesh, part, True, code, part_first)
            for m, part in piece.meshes.items():
                if m not in present.get(label, {}):
                    part.nodes = None
                    _set_visible(part.mesh, part, False, code, part_first)
        for piece in self.pieces:
            if piece.alive and not any(piece is p for p in pieces):
                piece.alive = False
                _set_visible(piece.xform, piece, False, code, first)
                for part in piece.meshes.values():
                    part.nodes = None
        return written

    def _match(self, labels: np.ndarray, cell_nodes: np.ndarray, alive: np.ndarray) -> list[_Piece]:
        """The prim of each piece now (index: its label): an old piece's where it shares the most nodes."""
        count = int(labels.max()) + 1 if alive.any() else 0
        live = np.flatnonzero(alive)
        # the piece of each node (pieces share no node but where they touch at a corner: then either)
        node_label = np.full(len(self.structure.node_rest), -1, dtype=np.int64)
        node_label[cell_nodes[live].ravel()] = np.repeat(labels[live], 4)
        nodes = np.flatnonzero(node_label >= 0)
        new_label, new_key = node_label[nodes], _rest_keys(np.asarray(self.structure.node_rest)[nodes])
        old = [p for p in self.pieces if p.alive]
        result: list[_Piece | None] = [None] * count
        old_keys = np.concatenate([p.keys for p in old]) if old else np.zeros(0, dtype=np.int64)
        if len(old_keys):
            old_index = np.concatenate([np.full(len(p.keys), i, dtype=np.int64) for i, p in enumerate(old)])
            sort = np.argsort(old_keys, kind="stable")
            old_keys, old_index = old_keys[sort], old_index[sort]
            at = np.minimum(np.searchsorted(old_keys, new_key), len(old_keys) - 1)
            hit = old_keys[at] == new_key
            pairs, shared = np.unique(new_label[hit] * len(old) + old_index[at[hit]], return_counts=True)
            taken = set()
            for k in np.argsort(-shared, kind="stable").tolist():
                n, o = divmod(int(pairs[k]), len(old))
                if result[n] is None and o not in taken:
                    result[n] = old[o]
                    taken.add(o)
        order = np.argsort(new_label, kind="stable")
        bounds = np.searchsorted(new_label[order], np.arange(count + 1))
        for n in range(count):
            if result[n] is None:
                result[n] = _Piece(self, len(self.pieces))
                self.pieces.append(result[n])
            result[n].keys = new_key[order[bounds[n] : bounds[n + 1]]]
        return result

    def _tissue_color(self, m: int, color_of: np.ndarray, faces: np.ndarray) -> np.ndarray:
        if m not in self.colors:
            if self.model is not None:
                self.colors[m] = color_of[np.unique(faces)].mean(axis=0)
            else:
                self.colors[m] = _PALETTE[m % len(_PALETTE)]
        return self.colors[m]


def _color_table(material_colors) -> dict:
    if isinstance(material_colors, dict):
        items = material_colors.items()
    else:
        items = enumerate(np.asarray(material_colors, dtype=np.float32).reshape(-1, 3))
    table = {}
    for m, c in items:
        c = np.asarray(c, dtype=np.float32).reshape(-1)
        if c.shape != (3,) or not np.isfinite(c).all():
            raise SceneError(f"Recorder.add: material_colors[{m!r}] must be an RGB triple, got {c.tolist()}")
        table[int(m)] = c
    return table


class _ToolTrack:
    """A rigid tool on a path: an Xform sampled per frame holding the tool's mesh."""

    def __init__(self, rec, base: str, tool, path, pose=None, clock=None):
        self.tool, self.path, self.pose, self.clock = tool, path, pose or path.pose, clock
        xform = UsdGeom.Xform.Define(rec.stage, base)
        self.translate = xform.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
        self.orient = xform.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
        mesh = UsdGeom.Mesh.Define(rec.stage, base + "/Mesh")
        v = _vec3f(tool.vertices)
        mesh.CreatePointsAttr(v)
        mesh.CreateFaceVertexCountsAttr(_ints(np.full(len(tool.faces), 3)))
        mesh.CreateFaceVertexIndicesAttr(_ints(tool.faces))
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(v))
        mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([Gf.Vec3f(*TOOL_COLOR)]))
        rec.looks.bind(mesh.GetPrim(), "Tool", TOOL_COLOR)
        self.visibility, self.shown = xform.CreateVisibilityAttr(), None

    def write(self, code: float, time: float) -> int:
        now = self.clock() if self.clock is not None else time
        shown = self.path.t0 - TOOL_PARK <= now <= self.path.t1 + TOOL_PARK
        if shown != self.shown:  # sampled where it changes: a tool away from its path is parked out of sight
            self.visibility.Set(UsdGeom.Tokens.inherited if shown else UsdGeom.Tokens.invisible, code)
            self.shown = shown
        pose = self.pose(now)
        self.translate.Set(Gf.Vec3d(*map(float, pose.position)), code)
        x, y, z, w = map(float, pose.rotation)
        self.orient.Set(Gf.Quatd(w, x, y, z), code)
        return 56


class Recorder:
    """Record simulations, cut meshes and tools into one animated USD stage.

    Args:
        path: ``.usda``/``.usdc``/``.usd`` target, written atomically by
            :meth:`close`; ``.usdc`` and ``.usd`` stream frames to disk as
            they are recorded (bounded memory), ``.usda`` holds them until close.
        fps: time codes (and frames) per second.
        up_axis: "Z" (the model's frame) or "Y" (the root prim then turns the model by -90 degrees
            about x, so that its z-up is the stage's y-up; the readers return points as authored,
            :meth:`~warpblob.tools.Path.from_usd` world poses, turned).
        meters_per_unit: stage metres per model unit (1 for a simulation in SI units).
        root: the default prim's name.
        flush_bytes: bytes of array data authored between saves of a streamed recording.

    Raises:
        SceneError: a bad suffix, a missing folder, bad ``fps``, ``up_axis``,
            ``meters_per_unit`` or ``root``.

    Example:
        >>> import os, tempfile
        >>> import warpblob as wb
        >>> import warpblob.usd
        >>> s = wb.TetStructure.from_tetmesh(wb.mesh.box_tetmesh((0, 0, 0), (1, 1, 1), (2, 2, 2)))
        >>> rec = wb.usd.Recorder(os.path.join(tempfile.mkdtemp(), "cut.usdc"))
        >>> _ = rec.add(s, name="Box")
        >>> rec.frame()
        >>> _ = wb.cut.cut(s, wb.cut.SweepSurface.plane((0.4, 0.5, 0.5), (1, 0.2, 0), 2.0))
        >>> rec.frame()
        >>> rec.close().suffix, wb.usd.load_tetmesh(rec.path, time=1).tet_count > 48
        ('.usdc', True)
    """

    def __init__(self, path, *, fps: float = 60.0, up_axis: str = "Z", meters_per_unit: float = 1.0,
                 root: str = "World", flush_bytes: int = FLUSH_BYTES):  # fmt: skip
        self.path = pathlib.Path(path)
        if self.path.suffix not in _SUFFIXES:
            raise SceneError(f"Recorder: path must end in one of {', '.join(_SUFFIXES)}, got {str(path)!r}")
        if isinstance(fps, bool) or not (isinstance(fps, (int, float)) and np.isfinite(fps) and fps > 0):
            raise SceneError(f"Recorder: fps must be a positive number, got {fps!r}")
        if up_axis not in ("Z", "Y"):
            raise SceneError(f"Recorder: up_axis must be 'Z' or 'Y', got {up_axis!r}")
        if not (isinstance(meters_per_unit, (int, float)) and np.isfinite(meters_per_unit) and meters_per_unit > 0):
            raise SceneError(f"Recorder: meters_per_unit must be a positive number, got {meters_per_unit!r}")
        if isinstance(flush_bytes, bool) or not isinstance(flush_bytes, (int, np.integer)) or flush_bytes < 1:
            raise SceneError(f"Recorder: flush_bytes must be a positive integer, got {flush_bytes!r}")
        check_target(self.path, "Recorder")
        self.fps = float(fps)
        self.root = "/" + _prim_name(root)
        self.flush_bytes = int(flush_bytes)
        self.streamed = self.path.suffix != ".usda"
        self._temporary = None
        if self.streamed:
            self._temporary = self.path.parent / f".{self.path.name}.{secrets.token_hex(4)}.tmp{self.path.suffix}"
        self.stage = new_stage(meters_per_unit=meters_per_unit, default_prim=root, start=0, end=0, fps=self.fps,
                               path=self._temporary)  # fmt: skip
        if up_axis == "Y":  # the model is z-up: the root turns it upright in a y-up stage
            UsdGeom.SetStageUpAxis(self.stage, UsdGeom.Tokens.y)
            UsdGeom.Xform(self.stage.GetPrimAtPath(self.root)).AddRotateXOp().Set(-90.0)
        self.looks = _Looks(self)
        self._tracks: list = []
        self._names: set[str] = set()
        self.frame_count = 0
        self.codes: list[float] = []
        self.saves = 0
        self._unsaved = 0
        self._closed = False

    def _name(self, name: str | None, default: str) -> str:
        name = _prim_name(name or default)
        base, k = name, 1
        while name in self._names:
            k += 1
            name = f"{base}{k}"
        self._names.add(name)
        return f"{self.root}/{name}"

    def _base(self, name, default, prim_path) -> str:
        if prim_path is None:
            return self._name(name, default)
        text = str(prim_path)
        if not Sdf.Path.IsValidPathString(text) or not Sdf.Path(text).IsAbsolutePath() or text == "/":
            raise SceneError(f"Recorder.add: prim_path must be an absolute prim path, got {prim_path!r}")
        return text

    def add(self, item, path=None, *, name: str | None = None, model=None, material_colors=None,
            prim_path: str | None = None) -> str:  # fmt: skip
        """Record ``item`` from the next frame on; returns its prim path.

        Args:
            item: a :class:`~warpblob.Simulation` (its volume, surfaces and tools),
                a :class:`~warpblob.mesh.TetStructure`, a tool (with ``path``), or a
                static :class:`~warpblob.mesh.SurfaceMesh` / :class:`~warpblob.mesh.TetMesh`.
            path: the tool's :class:`~warpblob.tools.Path` (tools only).
            name: prim name under the root (default by kind; made unique).
            model: BlobTree model whose colour field colours a cut surface (default: the simulation's).
            material_colors: tissue colours by material id, a dict ``{id: (r, g, b)}`` or an (M, 3)
                array (e.g. a tetrahedralized mesh's ``stats["materials"]``).
            prim_path: an absolute prim path for the item instead of ``<root>/<name>``.
        """
        from ..sim import Simulation
        from ..tools import Tool

        if self._closed:
            raise SceneError("Recorder.add: the recorder is closed")
        if isinstance(item, (Simulation, TetStructure)):
            base = self._base(name, "Simulation" if isinstance(item, Simulation) else "Volume", prim_path)
            UsdGeom.Xform.Define(self.stage, base)
            self._tracks.append(_VolumeTrack(self, base, item, model, material_colors))
            if isinstance(item, Simulation):
                records = (*item.tools, *item.cutters)
                if records:
                    UsdGeom.Scope.Define(self.stage, base + "/Tools")
                for k, record in enumerate(records):
                    pose = record.pose if hasattr(record, "pose") else record.path.pose
                    self._tracks.append(_ToolTrack(self, f"{base}/Tools/Tool{k}", record.tool, record.path, pose,
                                                   clock=lambda sim=item: sim.time))  # fmt: skip
            return base
        if isinstance(item, Tool):
            if path is None:
                raise SceneError("Recorder.add: a tool needs its path")
            base = self._base(name, "Tool", prim_path)
            self._tracks.append(_ToolTrack(self, base, item, path))
            return base
        if isinstance(item, SurfaceMesh):
            base = self._base(name, "Surface", prim_path)
            author_mesh(self.stage, base, item)
            return base
        if isinstance(item, TetMesh):
            base = self._base(name, "TetMesh", prim_path)
            author_tetmesh(self.stage, base, item)
            return base
        raise SceneError(f"Recorder.add: cannot record a {type(item).__name__}")

    def frame(self, time: float | None = None) -> None:
        """Write every recorded item's state now; ``time`` in seconds (default: the frame index / fps).

        A streamed recording is saved to disk once ``flush_bytes`` of arrays were authored since the last save.
        """
        if self._closed:
            raise SceneError("Recorder.frame: the recorder is closed")
        t = self.frame_count / self.fps if time is None else float(time)
        code = float(self.frame_count) if time is None else round(t * self.fps, 6)
        if self.codes and code <= self.codes[-1]:
            raise SceneError(f"Recorder.frame: time {t!r} s is not after the last frame's")
        for track in self._tracks:
            if isinstance(track, _ToolTrack):
                self._unsaved += track.write(code, t)
            else:
                self._unsaved += track.write(code)
        self.codes.append(code)
        self.frame_count += 1
        if self.streamed and self._unsaved >= self.flush_bytes:
            self._save()

    def _save(self) -> None:
        if self.codes:
            self.stage.SetStartTimeCode(self.codes[0])
            self.stage.SetEndTimeCode(self.codes[-1])
        if not self.stage.GetRootLayer().Save():
            raise OSError(f"Recorder: USD could not write {str(self._temporary)!r}")
        self.saves += 1
        self._unsaved = 0

    def close(self) -> pathlib.Path:
        """Set the time range and write the stage (atomically: renamed into place); returns its path."""
        if not self._closed:
            try:
                if self.streamed:
                    self._save()
                    os.replace(self._temporary, self.path)
                else:
                    if self.codes:
                        self.stage.SetStartTimeCode(self.codes[0])
                        self.stage.SetEndTimeCode(self.codes[-1])
                    export_atomically(self.stage.GetRootLayer(), self.path, "Recorder.close")
            finally:
                self._release()
        return self.path

    def discard(self) -> None:
        """Drop the recording: nothing is written and the temporary file is removed."""
        if not self._closed:
            self._release()

    def _release(self) -> None:
        self._closed = True
        self._tracks = []
        self.stage = None
        if self._temporary is not None and self._temporary.exists():
            self._temporary.unlink()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is None:
            self.close()
        else:
            self.discard()


# ---------------------------------------------------------------------------
# reading a recorded stage at a time code
# ---------------------------------------------------------------------------


def _stage(path, who):
    from .usd import open_stage

    return open_stage(path, who)


def _code(time) -> Usd.TimeCode:
    if time is None:  # the default value, else the first sample
        return Usd.TimeCode.EarliestTime()
    return time if isinstance(time, Usd.TimeCode) else Usd.TimeCode(float(time))


def _find(stage, schema, prim_path, source):
    if prim_path is not None:
        prim = stage.GetPrimAtPath(str(prim_path))
        if not prim:
            raise SceneError(f"{source}: no prim <{prim_path}>")
        return prim
    root = stage.GetDefaultPrim() or stage.GetPseudoRoot()
    for prim in Usd.PrimRange(root):
        if prim.IsA(schema):
            return prim
    kind = f"a {root.GetTypeName() or 'typeless'} prim" if not root.IsPseudoRoot() else "the stage"
    raise SceneError(f"{source}: no {schema.__name__} prim under <{root.GetPath()}> ({kind}, not a UsdGeom.{schema.__name__})")


def load_tetmesh_at(path, prim_path: str | None = None, *, time=None) -> TetMesh:
    """The :class:`~warpblob.mesh.TetMesh` of a USD file at time code ``time`` (default: the first sample).

    The prim: ``prim_path``, else the first TetMesh under the default prim
    (or on the stage). Tets of a ``leftHanded`` prim are reordered to positive
    orientation; material ids come from ``primvars:materialId`` or the
    ``warpblob:material`` attribute; nodes no tet uses (a recording keeps every
    node slot) are dropped.

    Raises:
        SceneError: the file is missing or not USD, holds no such TetMesh, or
            its arrays do not make a valid :class:`TetMesh`; the message names the file.
    """
    from .._errors import WarpblobError

    source = os.fspath(path)
    stage = _stage(source, "load_tetmesh")  # held: prims die with their stage
    prim = _find(stage, UsdGeom.TetMesh, prim_path, source)
    if not prim.IsA(UsdGeom.TetMesh):
        raise SceneError(f"{source}: prim <{prim.GetPath()}> is a {prim.GetTypeName() or 'typeless'} prim, not a TetMesh")
    code = _code(time)
    geom = UsdGeom.TetMesh(prim)
    points, tets = geom.GetPointsAttr().Get(code), geom.GetTetVertexIndicesAttr().Get(code)
    if points is None or tets is None:
        raise SceneError(f"{source}: TetMesh <{prim.GetPath()}> has no points or no tetVertexIndices")
    nodes = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    tets = np.asarray(tets, dtype=np.int32).reshape(-1, 4)
    if geom.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        tets = tets[:, [0, 2, 1, 3]]
    primvar = UsdGeom.PrimvarsAPI(geom).GetPrimvar(MATERIAL_PRIMVAR)
    attr = primvar.GetAttr() if primvar and primvar.HasValue() else prim.GetAttribute(MATERIAL_ATTR)
    value = attr.Get(code) if attr and attr.HasValue() else None
    material = None if value is None else np.asarray(value, dtype=np.int32)
    if len(tets) and tets.min() >= 0 and tets.max() < len(nodes):
        used = np.zeros(len(nodes), dtype=bool)
        used[tets.ravel()] = True
        if not used.all():
            remap = np.cumsum(used) - 1
            nodes, tets = nodes[used], remap[tets].astype(np.int32)
    try:
        return TetMesh(nodes, tets, material, stats={"source": source, "prim": str(prim.GetPath())})
    except WarpblobError as err:
        raise SceneError(f"{source}: TetMesh <{prim.GetPath()}>: {err}") from None


def _mesh_arrays(geom, code):
    v = np.asarray(geom.GetPointsAttr().Get(code) or [], dtype=np.float32).reshape(-1, 3)
    counts = np.asarray(geom.GetFaceVertexCountsAttr().Get(code) or [], dtype=np.int32)
    if np.any(counts != 3):
        raise SceneError(f"{geom.GetPath()}.faceVertexCounts: only triangles are supported")
    f = np.asarray(geom.GetFaceVertexIndicesAttr().Get(code) or [], dtype=np.int32).reshape(-1, 3)
    api = UsdGeom.PrimvarsAPI(geom)
    color = api.GetPrimvar("displayColor").Get(code) if api.HasPrimvar("displayColor") else None
    colors = np.asarray(color, dtype=np.float32) if color is not None and len(color) == len(v) else np.full_like(v, 0.8)
    cut = api.GetPrimvar(IS_CUT_PRIMVAR).Get(code) if api.HasPrimvar(IS_CUT_PRIMVAR) else None
    cut = np.asarray(cut, dtype=bool) if cut is not None and len(cut) == len(f) else np.zeros(len(f), dtype=bool)
    node = api.GetPrimvar(NODE_PRIMVAR).Get(code) if api.HasPrimvar(NODE_PRIMVAR) else None
    node = np.asarray(node, dtype=np.int64) if node is not None and len(node) == len(v) else None
    return v, f, colors, cut, node


def _visible_meshes(prim, code):
    """The visible Mesh prims at and under ``prim`` at ``code`` (visibility and purpose as a viewer computes them)."""
    out = []
    for p in Usd.PrimRange(prim):
        if p.IsA(UsdGeom.Mesh):
            img = UsdGeom.Imageable(p)
            if img.ComputeVisibility(code) != UsdGeom.Tokens.invisible and img.ComputePurpose() != UsdGeom.Tokens.guide:
                out.append(p)
    return out


def load_mesh_at(path, prim_path: str | None = None, *, time=None) -> SurfaceMesh:
    """The :class:`~warpblob.mesh.SurfaceMesh` of a USD file at time code ``time``, ``is_cut`` from its primvar.

    ``prim_path`` may name a Mesh, or any prim above meshes (a recorded
    track, its ``Pieces``): then every Mesh under it visible at ``time`` is
    joined into one mesh, the vertices that pieces' meshes share (by
    ``primvars:warpblob:node``) merged. Without ``prim_path``: the first Mesh
    under the default prim, or, when that is a recorded piece's, every piece
    of its track.

    Raises:
        SceneError: the file is missing or not USD, or holds no such mesh.
    """
    source = os.fspath(path)
    stage = _stage(source, "load_mesh")
    code = _code(time)
    prim = _find(stage, UsdGeom.Mesh, prim_path, source)
    if prim_path is None:
        pieces = prim.GetParent().GetParent()
        if pieces and pieces.GetName() == "Pieces":
            prim = pieces
    if prim.IsA(UsdGeom.Mesh):
        v, f, colors, cut, _ = _mesh_arrays(UsdGeom.Mesh(prim), code)
        return SurfaceMesh(v, f, _normals(v, f), colors, is_cut=cut if UsdGeom.PrimvarsAPI(prim).HasPrimvar(IS_CUT_PRIMVAR) else None)
    parts = [_mesh_arrays(UsdGeom.Mesh(p), code) for p in _visible_meshes(prim, code)]
    if not parts:
        raise SceneError(f"{source}: no visible Mesh under <{prim.GetPath()}> at time {time!r}")
    vs, fs, cs, cuts, keys, offset = [], [], [], [], [], 0
    for k, (v, f, c, cut, node) in enumerate(parts):
        vs.append(v), fs.append(f + offset), cs.append(c), cuts.append(cut)
        keys.append(node if node is not None else -1 - offset - np.arange(len(v), dtype=np.int64))
        offset += len(v)
    key = np.concatenate(keys)
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    v = np.concatenate(vs)[first]
    f = inverse.reshape(-1)[np.concatenate(fs)].astype(np.int32)
    return SurfaceMesh(v, f, _normals(v, f), np.concatenate(cs)[first], is_cut=np.concatenate(cuts))


def _normals(v, f):
    n = np.zeros_like(v)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    for j in range(3):
        np.add.at(n, f[:, j], fn)
    return (n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)).astype(np.float32)
