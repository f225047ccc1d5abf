"""BlobTree models as USD scenes, in the format of ``docs/usd_format.md``.

A model is a prim hierarchy under one root prim. Operators, warps and
primitives are ``Xform`` prims: the token ``warpblob:kind`` names the node and
``warpblob:<parameter>`` attributes hold its constructor arguments (same
names as in Python). Operands are the child prims that carry ``warpblob:``
attributes, in the order of their ``warpblob:order``. A :class:`Transform`
node has no prim of its own: it is the ``xformOp`` of its child's prim.
Primitive colours are ``primvars:displayColor``, and every primitive prim has
a ``guide`` child (a gprim of purpose ``guide``) that previews it in DCC
tools; the reader ignores guides.

Writing authors an ``Sdf`` layer in memory (the Usd API is too slow for the
14,600 prims of ``towers``), exports it to a temporary file beside the
target and renames that into place. Subtrees that occur more than once are
written once, under the root's ``class "prototypes"``, and referenced.
Reading lets USD compose the stage first, so references, inherits, payloads
and variants all work in hand-written scenes.
"""

from __future__ import annotations

import inspect
import os
import pathlib
import re
import secrets
from dataclasses import dataclass

import numpy as np
from pxr import Gf, Pcp, Sdf, Tf, Usd, UsdGeom, Vt

from .._errors import ModelError, SceneError
from ..tree import (
    ISO_DISTANCE,
    Bend,
    Blend,
    Box,
    Cone,
    Cylinder,
    Difference,
    Disc,
    Inflate,
    Intersection,
    Node,
    Point,
    Polygon,
    Revolve,
    Ring,
    Segment,
    Sketch,
    SmoothBlend,
    Sweep,
    Taper,
    Transform,
    Triangle,
    Twist,
    Union,
)
from ..tree._primitives import DEFAULT_COLOR

__all__ = ["save_model", "load_model", "save_mesh", "load_mesh", "save_tetmesh", "FORMAT_VERSION", "METERS_PER_UNIT"]

#: Version written to ``warpblob:version``; the reader refuses newer files.
FORMAT_VERSION = 1
#: Default stage ``metersPerUnit``: one model unit is one centimetre.
METERS_PER_UNIT = 0.01
#: the uniform bool primvar (``primvars:isCut``) that marks the faces a blade made
IS_CUT_PRIMVAR = "isCut"
#: the custom int array attribute of a static TetMesh prim: the material id of each tet
MATERIAL_ATTR = "warpblob:material"

_NS = "warpblob"
_KIND = "warpblob:kind"
_ORDER = "warpblob:order"
_VERSION = "warpblob:version"
_COLOR = "primvars:displayColor"
_PROTOTYPES = "prototypes"
_GUIDE = "guide"
_SUFFIXES = (".usda", ".usdc", ".usd")
#: vertices of the circles drawn by disc and ring guides
_CIRCLE_VERTICES = 24

_T = Sdf.ValueTypeNames


# ---------------------------------------------------------------------------
# the table of node kinds: one entry drives the writer, the reader and the docs
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Type:
    """A parameter type: the Sdf type written, the types read, the value's shape."""

    name: str
    sdf: Sdf.ValueTypeName
    accepts: tuple  # Tf types (role-free) the reader takes
    shape: tuple | None  # () scalar, (3,) vector, (None, k) array of k-vectors; None: not a number

    def to_usd(self, value):
        if self.shape == ():
            return float(value)
        arr = np.ascontiguousarray(value, dtype=np.float64)
        if self.shape == (3,):
            return Gf.Vec3d(*arr.tolist())
        return (Vt.Vec3dArray if self.shape[1] == 3 else Vt.Vec2dArray).FromNumpy(arr)


def _accepts(*names):
    return tuple(n.type for n in names)


_TOKEN = _Type("token", _T.Token, _accepts(_T.Token), None)
_INT = _Type("int", _T.Int, _accepts(_T.Int), None)
_DOUBLE = _Type("double", _T.Double, _accepts(_T.Double, _T.Float, _T.Half), ())
_DOUBLE3 = _Type("double3", _T.Double3, _accepts(_T.Double3, _T.Float3, _T.Half3), (3,))
_DOUBLE3_ARRAY = _Type(
    "double3[]", _T.Double3Array, _accepts(_T.Double3Array, _T.Float3Array, _T.Half3Array), (None, 3)
)
_DOUBLE2_ARRAY = _Type(
    "double2[]", _T.Double2Array, _accepts(_T.Double2Array, _T.Float2Array, _T.Half2Array), (None, 2)
)


@dataclass(frozen=True)
class _Param:
    """One constructor parameter stored as the attribute ``warpblob:<name>``."""

    name: str
    type: _Type
    default: object = None  # None: required

    @property
    def attr(self) -> str:
        return f"{_NS}:{self.name}"

    def value(self, node) -> np.ndarray:
        """The parameter of ``node`` as written (float64)."""
        if self.name == "sketch":
            return node.sketch.points
        if self.name in ("p0", "p1", "p2"):  # a Triangle keeps its corners as the rows of .points
            return node.points[int(self.name[1])]
        return np.asarray(getattr(node, self.name), dtype=np.float64)


@dataclass(frozen=True)
class _Kind:
    cls: type
    params: tuple
    min_operands: int
    max_operands: int | None  # None: no limit; 0: a primitive

    @property
    def is_primitive(self) -> bool:
        return self.max_operands == 0


def _kind(cls, operands, **types):
    """Table entry of ``cls``; defaults come from the constructor's signature."""
    signature = inspect.signature(cls.__init__).parameters
    params = []
    for name, typ in types.items():
        default = signature[name].default if name in signature else inspect.Parameter.empty
        params.append(_Param(name, typ, None if default is inspect.Parameter.empty else default))
    return _Kind(cls, tuple(params), *operands)


_LEAF = (0, 0)
_ANY = (1, None)
_ONE = (1, 1)
_KINDS = {
    "point": _kind(Point, _LEAF, center=_DOUBLE3, radius=_DOUBLE),
    "segment": _kind(Segment, _LEAF, a=_DOUBLE3, b=_DOUBLE3, radius=_DOUBLE),
    "disc": _kind(Disc, _LEAF, center=_DOUBLE3, normal=_DOUBLE3, disc_radius=_DOUBLE, radius=_DOUBLE),
    "ring": _kind(Ring, _LEAF, center=_DOUBLE3, normal=_DOUBLE3, ring_radius=_DOUBLE, radius=_DOUBLE),
    "cylinder": _kind(Cylinder, _LEAF, a=_DOUBLE3, b=_DOUBLE3, cylinder_radius=_DOUBLE, radius=_DOUBLE),
    "cone": _kind(
        Cone, _LEAF, a=_DOUBLE3, b=_DOUBLE3, radius_a=_DOUBLE, radius_b=_DOUBLE, radius=_DOUBLE
    ),
    "triangle": _kind(Triangle, _LEAF, p0=_DOUBLE3, p1=_DOUBLE3, p2=_DOUBLE3, radius=_DOUBLE),
    "polygon": _kind(Polygon, _LEAF, points=_DOUBLE3_ARRAY, radius=_DOUBLE),
    "box": _kind(Box, _LEAF, center=_DOUBLE3, half_extents=_DOUBLE3, radius=_DOUBLE),
    "inflate": _kind(Inflate, _LEAF, sketch=_DOUBLE2_ARRAY, thickness=_DOUBLE, radius=_DOUBLE),
    "revolve": _kind(Revolve, _LEAF, sketch=_DOUBLE2_ARRAY, axis=_DOUBLE3, center=_DOUBLE3, radius=_DOUBLE),
    "sweep": _kind(Sweep, _LEAF, sketch=_DOUBLE2_ARRAY, path=_DOUBLE3_ARRAY, radius=_DOUBLE),
    "blend": _kind(Blend, _ANY),
    "union": _kind(Union, _ANY),
    "intersection": _kind(Intersection, _ANY),
    "difference": _kind(Difference, (2, 2)),
    "smooth_blend": _kind(SmoothBlend, (2, None), k=_DOUBLE),
    "twist": _kind(Twist, _ONE, axis=_DOUBLE3, rate=_DOUBLE),
    "taper": _kind(Taper, _ONE, axis=_DOUBLE3, slope=_DOUBLE),
    "bend": _kind(Bend, _ONE, direction=_DOUBLE3, up=_DOUBLE3, rate=_DOUBLE),
}
_KIND_OF_CLASS = {spec.cls: name for name, spec in _KINDS.items()}


# ---------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------


def save_model(
    model: Node,
    path,
    *,
    prim_path: str = "/Model",
    meters_per_unit: float = METERS_PER_UNIT,
    doc: str | None = None,
) -> pathlib.Path:
    """Write ``model`` to the USD file ``path`` (``.usda`` text, ``.usdc``/``.usd`` binary).

    The file is written to a temporary file in the same directory and renamed
    over ``path``, so ``path`` is either left untouched or holds the whole
    model. The stage has upAxis Z, ``metersPerUnit = meters_per_unit`` and the
    root prim as its default prim. Coordinates are written as they are (one
    model unit is one stage unit).

    Args:
        model: the BlobTree.
        path: target file; its folder must exist.
        prim_path: the root prim, a single name under the pseudo-root.
        meters_per_unit: stage metres per model unit (default 0.01: centimetres).
        doc: optional stage documentation string.

    Returns:
        ``path`` as a :class:`pathlib.Path`.

    Raises:
        ModelError: ``model`` is not a tree of warpblob nodes.
        SceneError: bad ``path`` suffix, a missing folder, bad ``prim_path``
            or ``meters_per_unit``.
        OSError: the file could not be written.

    Example:
        >>> import tempfile, os, warpblob as wb, warpblob.usd
        >>> path = os.path.join(tempfile.mkdtemp(), "peanut.usda")
        >>> m = wb.usd.load_model(wb.usd.save_model(wb.scenes.peanut(), path))
        >>> m.primitive_count()
        2
    """
    target = check_target(path, "save_model")
    root = Sdf.Path(str(prim_path)) if Sdf.Path.IsValidPathString(str(prim_path)) else Sdf.Path()
    if not (root.IsRootPrimPath() and root.IsAbsolutePath()):
        raise SceneError(f"save_model: prim_path must be a root prim path like '/Model', got {prim_path!r}")
    if not (isinstance(meters_per_unit, (int, float)) and np.isfinite(meters_per_unit) and meters_per_unit > 0):
        raise SceneError(f"save_model: meters_per_unit must be a positive number, got {meters_per_unit!r}")
    if not isinstance(model, Node):
        raise ModelError(f"save_model: model must be a warpblob Node, got {model!r}")
    layer = _author_layer(model, root, float(meters_per_unit), doc)
    return export_atomically(layer, target, "save_model")


def check_target(path, who: str) -> pathlib.Path:
    """``path`` as a :class:`pathlib.Path` once it is fit to write a USD file to.

    Writers call it before any work, so a bad path costs nothing.

    Raises:
        SceneError: the suffix is not ``.usda``, ``.usdc`` or ``.usd``, the
            folder does not exist, or ``path`` is a folder.
    """
    target = pathlib.Path(path)
    if target.suffix not in _SUFFIXES:
        raise SceneError(f"{who}: path must end in one of {', '.join(_SUFFIXES)}, got {str(path)!r}")
    if not target.parent.is_dir():
        raise SceneError(f"{who}: folder {str(target.parent)!r} of {str(path)!r} does not exist")
    if target.is_dir():
        raise SceneError(f"{who}: {str(path)!r} is a folder")
    return target


def export_atomically(layer, target, who: str) -> pathlib.Path:
    """Export ``layer`` to a temporary file beside ``target``, then rename it into place.

    ``target`` is either left untouched or complete, and no temporary file
    is left behind.

    Raises:
        SceneError: see :func:`check_target`.
        OSError: USD could not write the file, or the rename failed.
    """
    target = check_target(target, who)
    temporary = target.parent / f".{target.name}.{secrets.token_hex(4)}.tmp{target.suffix}"
    try:
        if not layer.Export(str(temporary)):
            raise OSError(f"{who}: USD could not write {str(temporary)!r}")
        os.replace(temporary, target)
    except Tf.ErrorException as err:
        raise OSError(f"{who}: USD could not write {str(target)!r}: {_one_line(err)}") from None
    finally:
        if temporary.exists():
            temporary.unlink()
    return target


def new_stage(*, meters_per_unit: float = METERS_PER_UNIT, default_prim: str | None = None, start=None, end=None,
              fps: float = 24.0, path=None):  # fmt: skip
    """A stage with upAxis Z, metersPerUnit, time codes and frames per second set.

    Args:
        meters_per_unit: stage metres per model unit.
        default_prim: name of the root prim to make the default prim (defined as an Xform if missing).
        start, end: start and end time codes, for animated stages.
        fps: ``timeCodesPerSecond`` and ``framesPerSecond``.
        path: the new layer's file (``Usd.Stage.CreateNew``; written by the layer's ``Save``);
            default: in memory.
    """
    stage = Usd.Stage.CreateInMemory() if path is None else Usd.Stage.CreateNew(os.fspath(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    if start is not None:
        stage.SetStartTimeCode(start)
        stage.SetEndTimeCode(end if end is not None else start)
    if default_prim:
        prim = stage.GetPrimAtPath("/" + default_prim)
        if not prim:
            prim = UsdGeom.Xform.Define(stage, "/" + default_prim).GetPrim()
        stage.SetDefaultPrim(prim)
    return stage


def author_mesh(stage, path: str, mesh):
    """Define a ``UsdGeom.Mesh`` at ``path`` from a :class:`~warpblob.mesh.SurfaceMesh`.

    Writes points, faceVertexCounts/Indices (counter-clockwise, rightHanded),
    vertex normals, vertex ``primvars:displayColor``, the extent and, for the
    boundary of a cut tet mesh (``mesh.is_cut`` set), the uniform bool
    primvar :data:`IS_CUT_PRIMVAR` (one value per face).
    """
    geom = UsdGeom.Mesh.Define(stage, path)
    points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.vertices, dtype=np.float32))
    geom.CreatePointsAttr(points)
    geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(mesh.face_count, 3, dtype=np.int32)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.faces, dtype=np.int32).ravel()))
    geom.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    geom.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.normals, dtype=np.float32)))
    geom.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    color = geom.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex)
    color.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.colors, dtype=np.float32)))
    geom.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
    if getattr(mesh, "is_cut", None) is not None:
        cut = UsdGeom.PrimvarsAPI(geom).CreatePrimvar(IS_CUT_PRIMVAR, Sdf.ValueTypeNames.BoolArray, UsdGeom.Tokens.uniform)
        cut.Set(Vt.BoolArray.FromNumpy(np.ascontiguousarray(mesh.is_cut, dtype=bool)))
    return geom


def author_tetmesh(stage, path: str, mesh):
    """Define a ``UsdGeom.TetMesh`` at ``path`` from a :class:`~warpblob.mesh.TetMesh`.

    Writes points, tetVertexIndices, surfaceFaceVertexIndices (the boundary,
    counter-clockwise from outside), orientation rightHanded, the extent and,
    when the mesh has one, the int array ``warpblob:material`` (one per tet).
    """
    geom = UsdGeom.TetMesh.Define(stage, path)
    points = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(mesh.nodes, dtype=np.float32))
    geom.CreatePointsAttr(points)
    geom.CreateTetVertexIndicesAttr(Vt.Vec4iArray.FromNumpy(np.ascontiguousarray(mesh.tets, dtype=np.int32)))
    faces = np.ascontiguousarray(mesh.surface_faces(), dtype=np.int32)
    geom.CreateSurfaceFaceVertexIndicesAttr(Vt.Vec3iArray.FromNumpy(faces))
    geom.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    geom.CreateExtentAttr(UsdGeom.PointBased.ComputeExtent(points))
    if mesh.material is not None:
        attr = geom.GetPrim().CreateAttribute(MATERIAL_ATTR, Sdf.ValueTypeNames.IntArray, custom=True)
        attr.Set(Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.material, dtype=np.int32)))
    return geom


def save_mesh(mesh, path, *, prim_path: str = "/Surface", meters_per_unit: float = METERS_PER_UNIT) -> pathlib.Path:
    """Write a :class:`~warpblob.mesh.SurfaceMesh` as a ``UsdGeom.Mesh`` stage (atomically).

    Args:
        mesh: the mesh (see :func:`author_mesh` for what is written).
        path: a ``.usda``, ``.usdc`` or ``.usd`` file; its folder must exist.
        prim_path: the Mesh prim, a root prim (the stage's default prim).
        meters_per_unit: stage metres per model unit.

    Returns:
        ``path`` as a :class:`pathlib.Path`.

    Raises:
        SceneError: bad suffix, missing folder or bad ``prim_path``.
        OSError: the file could not be written.

    Example:
        >>> import tempfile, os, warpblob as wb, warpblob.usd
        >>> mesh = wb.polygonize(wb.scenes.peanut(), cellsize=0.2)
        >>> path = wb.usd.save_mesh(mesh, os.path.join(tempfile.mkdtemp(), "peanut.usda"))
        >>> wb.usd.load_mesh(path).face_count == mesh.face_count
        True
    """
    target = check_target(path, "save_mesh")
    name = str(prim_path).strip("/")
    if not name or "/" in name or not Sdf.Path.IsValidIdentifier(name):
        raise SceneError(f"save_mesh: prim_path must be a root prim path like '/Surface', got {prim_path!r}")
    stage = new_stage(meters_per_unit=meters_per_unit)
    author_mesh(stage, "/" + name, mesh)
    stage.SetDefaultPrim(stage.GetPrimAtPath("/" + name))
    return export_atomically(stage.GetRootLayer(), target, "save_mesh")


def save_tetmesh(mesh, path, *, prim_path: str = "/TetMesh", meters_per_unit: float = METERS_PER_UNIT) -> pathlib.Path:
    """Write a :class:`~warpblob.mesh.TetMesh` as a ``UsdGeom.TetMesh`` stage (``.usda`` text, ``.usdc``/``.usd`` binary).

    The prim gets ``points``, ``tetVertexIndices``, ``surfaceFaceVertexIndices``
    (:meth:`~warpblob.mesh.TetMesh.surface_faces`), ``extent`` and, when
    present, the int array ``warpblob:material``. The stage has upAxis Z,
    ``metersPerUnit`` and the root prim of ``prim_path`` as default prim. The
    file is written beside ``path`` under a temporary name and renamed over
    it, so ``path`` is either untouched or complete.

    Args:
        mesh: the tet mesh.
        path: target file; its folder must exist.
        prim_path: absolute path of the TetMesh prim.
        meters_per_unit: stage metres per model unit (default 0.01: centimetres).

    Returns:
        ``path`` as a :class:`pathlib.Path`.

    Raises:
        SceneError: bad suffix or missing folder (checked before any work), bad
            prim path or ``meters_per_unit``.
        OSError: USD could not write.

    Example:
        >>> import os, tempfile, warpblob as wb, warpblob.usd
        >>> mesh = wb.mesh.box_tetmesh((0, 0, 0), (1, 1, 1), (2, 2, 2))
        >>> path = wb.usd.save_tetmesh(mesh, os.path.join(tempfile.mkdtemp(), "box.usda"))
        >>> wb.usd.load_tetmesh(path).tet_count == mesh.tet_count
        True
    """
    target = check_target(path, "save_tetmesh")
    text = str(prim_path)
    if not Sdf.Path.IsValidPathString(text) or not Sdf.Path(text).IsAbsolutePath() or text == "/":
        raise SceneError(f"save_tetmesh: prim_path must be an absolute prim path, got {prim_path!r}")
    mpu = METERS_PER_UNIT if meters_per_unit is None else meters_per_unit
    if isinstance(mpu, bool) or not (isinstance(mpu, (int, float)) and np.isfinite(mpu) and mpu > 0):
        raise SceneError(f"save_tetmesh: meters_per_unit must be a positive number, got {mpu!r}")
    stage = new_stage(meters_per_unit=float(mpu))
    author_tetmesh(stage, text, mesh)
    stage.SetDefaultPrim(stage.GetPrimAtPath(Sdf.Path(text).GetPrefixes()[0]))
    return export_atomically(stage.GetRootLayer(), target, "save_tetmesh")


def open_stage(path, who: str):
    """Open and compose the USD file ``path``, or raise a :class:`SceneError` naming it.

    Every reader goes through here, so a missing file, a folder or a file
    that is not USD fails the same way whichever reader was called.
    """
    source = os.fspath(path)
    if not os.path.exists(source):
        raise SceneError(f"{who}: {source}: no such file")
    if not os.path.isfile(source):
        raise SceneError(f"{who}: {source}: not a file")
    try:
        stage = Usd.Stage.Open(source, Usd.Stage.LoadAll)
    except Tf.ErrorException as err:
        raise SceneError(f"{who}: {source}: not a readable USD file ({_one_line(err)})") from None
    if stage is None:
        raise SceneError(f"{who}: {source}: not a readable USD file")
    return stage


def load_mesh(path, prim_path: str | None = None):
    """Read a triangle ``UsdGeom.Mesh`` as a :class:`~warpblob.mesh.SurfaceMesh`.

    Args:
        path: a USD file.
        prim_path: the Mesh prim; default: the default prim, or the only root
            prim of a stage without one.

    Returns:
        The mesh (normals zero and colours white where the prim has none).

    Raises:
        SceneError: the file is missing or not USD, the prim is missing or not
            a triangle ``UsdGeom.Mesh``; the message names the file.

    Example:
        >>> import warpblob as wb, warpblob.usd
        >>> try:
        ...     wb.usd.load_mesh("no/such/mesh.usda")
        ... except wb.SceneError as err:
        ...     print(err)
        load_mesh: no/such/mesh.usda: no such file
    """
    from ..mesh import SurfaceMesh

    source = os.fspath(path)
    stage = open_stage(source, "load_mesh")
    prim = _root_prim(stage, source, prim_path)
    if not prim.IsA(UsdGeom.Mesh):
        raise SceneError(f"{source}: prim <{prim.GetPath()}> is {_type_of(prim)}, not a UsdGeom.Mesh")
    geom = UsdGeom.Mesh(prim)
    counts = np.asarray(geom.GetFaceVertexCountsAttr().Get() or [], dtype=np.int32)
    if np.any(counts != 3):
        raise SceneError(f"{source}: {prim.GetPath()}.faceVertexCounts: only triangles are supported")
    faces = np.asarray(geom.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int32).reshape(-1, 3)
    points = np.asarray(geom.GetPointsAttr().Get() or [], dtype=np.float32).reshape(-1, 3)
    normals = np.asarray(geom.GetNormalsAttr().Get() or np.zeros((len(points), 3)), dtype=np.float32).reshape(-1, 3)
    colors = geom.GetDisplayColorPrimvar().Get()
    colors = np.asarray(colors if colors is not None and len(colors) == len(points) else np.ones((len(points), 3)), dtype=np.float32)
    cut = UsdGeom.PrimvarsAPI(geom).GetPrimvar(IS_CUT_PRIMVAR)
    is_cut = cut.Get() if cut and cut.HasValue() else None
    is_cut = np.asarray(is_cut, dtype=bool) if is_cut is not None and len(is_cut) == len(faces) else None
    return SurfaceMesh(points, faces, normals, colors.reshape(-1, 3), is_cut=is_cut)


def _unwrap(node):
    """``(matrix or None, node)``: the Transform around a node is its prim's xformOp."""
    if isinstance(node, Transform):
        return node.matrix, node.child
    return None, node


def _spec_of(node) -> tuple[str, _Kind]:
    name = _KIND_OF_CLASS.get(type(node))
    if name is None:
        raise ModelError(f"save_model: no USD form for node type {type(node).__name__} ({node!r})")
    return name, _KINDS[name]


def _structure_keys(model) -> tuple[dict, set]:
    """Structural key of every prim-node, and the keys worth sharing.

    Two subtrees with equal keys are equal node for node (kinds, parameters,
    colours, transforms). A key is shared when it is an operator's and more
    than one operand slot of the written tree (counting a shared subtree
    once) holds it.
    """
    ids: dict[tuple, int] = {}
    key_of: dict[int, int] = {}  # id(node) -> key
    operands_of: dict[int, list] = {}  # key -> operand keys
    stack = [(_unwrap(model)[1], False)]
    while stack:
        node, done = stack.pop()
        if id(node) in key_of:
            continue
        children = [_unwrap(c) for c in node.children]
        if not done:
            stack.append((node, True))
            stack.extend((c, False) for _, c in reversed(children))
            continue
        kind, spec = _spec_of(node)
        parts = [kind]
        for p in spec.params:
            v = np.asarray(p.value(node), dtype=np.float64)
            parts.append((v.shape, v.tobytes()))
        if spec.is_primitive:
            parts.append(np.asarray(node.color, dtype=np.float64).tobytes())
        for m, c in children:
            parts.append((None if m is None else m.tobytes(), key_of[id(c)]))
        key = ids.setdefault(tuple(parts), len(ids))
        key_of[id(node)] = key
        operands_of[key] = [key_of[id(c)] for _, c in children]
    uses: dict[int, int] = {}
    seen = set()
    pending = [key_of[id(_unwrap(model)[1])]]
    while pending:
        key = pending.pop()
        if key in seen:
            continue
        seen.add(key)
        for k in operands_of[key]:
            uses[k] = uses.get(k, 0) + 1
            pending.append(k)
    shared = {k for k, n in uses.items() if n > 1 and operands_of[k]}
    return key_of, shared


def _set(spec, name, type_name, value, *, uniform=False, interpolation=None):
    attr = Sdf.AttributeSpec(spec, name, type_name, Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
    attr.default = value
    if interpolation is not None:
        attr.SetInfo("interpolation", interpolation)


def _set_transform(spec, matrix):
    """Author ``matrix`` (column-vector, child to parent) as the prim's one xformOp."""
    if np.array_equal(matrix[:3, :3], np.eye(3)):
        op = "xformOp:translate"
        _set(spec, op, _T.Double3, Gf.Vec3d(*matrix[:3, 3].tolist()))
    else:
        op = "xformOp:transform"
        # USD multiplies row vectors on the left: its matrix is the transpose of ours
        _set(spec, op, _T.Matrix4d, Gf.Matrix4d(matrix.T.tolist()))
    _set(spec, "xformOpOrder", _T.TokenArray, Vt.TokenArray([op]), uniform=True)


def _author_layer(model, root: Sdf.Path, meters_per_unit: float, doc) -> Sdf.Layer:
    key_of, shared = _structure_keys(model)
    layer = Sdf.Layer.CreateAnonymous(".usda")
    prototypes: dict[int, Sdf.Path] = {}  # structural key -> prototype prim
    later = []  # prototypes to write once the model's own prims are done
    with Sdf.ChangeBlock():
        layer.defaultPrim = root.name
        layer.pseudoRoot.SetInfo(UsdGeom.Tokens.upAxis, UsdGeom.Tokens.z)
        layer.pseudoRoot.SetInfo(UsdGeom.Tokens.metersPerUnit, meters_per_unit)
        if doc:
            layer.documentation = str(doc)
        # a task: (node or Transform, prim path, operand order or None, written as a prototype)
        tasks = [(model, root, None, False)]
        while tasks:
            node, path, order, is_prototype = tasks.pop()
            matrix, node = _unwrap(node)
            spec = Sdf.CreatePrimInLayer(layer, path)
            spec.specifier = Sdf.SpecifierDef
            spec.typeName = "Xform"
            if path == root:
                spec.kind = "component"
                _set(spec, _VERSION, _T.Int, FORMAT_VERSION, uniform=True)
            if order is not None:
                _set(spec, _ORDER, _T.Int, order, uniform=True)
            if matrix is not None:
                _set_transform(spec, matrix)
            key = key_of[id(node)]
            if key in shared and not is_prototype:
                if key not in prototypes:
                    prototypes[key] = root.AppendChild(_PROTOTYPES).AppendChild(f"{node.kind}_{len(prototypes)}")
                    later.append((node, prototypes[key], None, True))
                spec.referenceList.Prepend(Sdf.Reference(primPath=prototypes[key]))
            else:
                _author_node(spec, node)
                for i in reversed(range(len(node.children))):
                    child = node.children[i]
                    tasks.append((child, path.AppendChild(f"{_unwrap(child)[1].kind}_{i}"), i, False))
            if not tasks and later:
                if not layer.GetPrimAtPath(root.AppendChild(_PROTOTYPES)):
                    # last child of the root; abstract, so neither drawn nor read as an operand
                    Sdf.PrimSpec(layer.GetPrimAtPath(root), _PROTOTYPES, Sdf.SpecifierClass)
                tasks.append(later.pop(0))
    return layer


def _author_node(spec, node):
    """Kind, parameters and, for a primitive, colour and guide."""
    kind, kind_spec = _spec_of(node)
    _set(spec, _KIND, _T.Token, kind, uniform=True)
    for p in kind_spec.params:
        _set(spec, p.attr, p.type.sdf, p.type.to_usd(p.value(node)))
    if kind_spec.is_primitive:
        _set(spec, _COLOR, _T.Color3fArray, Vt.Vec3fArray([Gf.Vec3f(*node.color.tolist())]))
        _author_guide(spec, node)


# --- guides -----------------------------------------------------------------


def _circle(frame, radius):
    t = np.linspace(0.0, 2.0 * np.pi, _CIRCLE_VERTICES, endpoint=False)
    local = np.column_stack([radius * np.cos(t), radius * np.sin(t), np.zeros_like(t), np.ones_like(t)])
    return (local @ frame.T)[:, :3]


def _guide_shape(node):
    """``(gprim type, attributes)`` of the preview of primitive ``node``.

    Lines and points are drawn as thick as a lone primitive's surface
    (``ISO_DISTANCE * R`` from the skeleton); flat skeletons as meshes.
    """
    surface = ISO_DISTANCE * node.radius
    if isinstance(node, Point):
        c = node.center
        return "Sphere", {"radius": surface, "translate": c}
    if isinstance(node, Box):
        return "Cube", {"translate": node.center, "scale": node.half_extents + surface}
    if isinstance(node, Cone):  # and Cylinder
        widths = 2.0 * (np.array([node.radius_a, node.radius_b]) + surface)
        return "BasisCurves", {"points": np.array([node.a, node.b]), "widths": widths}
    if isinstance(node, Segment):
        return "BasisCurves", {"points": np.array([node.a, node.b]), "widths": [2.0 * surface]}
    if isinstance(node, Ring):
        return "BasisCurves", {"points": _circle(node.frame, node.ring_radius), "widths": [2.0 * surface], "wrap": True}
    if isinstance(node, Disc):
        return "Mesh", {"points": _circle(node.frame, node.disc_radius)}
    if isinstance(node, Polygon):  # and Triangle
        return "Mesh", {"points": node.points}
    if isinstance(node, Sweep):
        return "BasisCurves", {"points": node.path, "widths": [2.0 * surface]}
    # Inflate draws its contour at z = 0, Revolve its profile in the frame's xz plane
    u = node.sketch.points
    zero = np.zeros(len(u))
    local = np.column_stack([u[:, 0], u[:, 1], zero] if isinstance(node, Inflate) else [u[:, 0], zero, u[:, 1]])
    points = local @ node.frame[:3, :3].T + node.frame[:3, 3]
    return "BasisCurves", {"points": points, "widths": [2.0 * surface], "wrap": True}


def _extent(points, pad=0.0):
    p = np.asarray(points, dtype=np.float64)
    return Vt.Vec3fArray.FromNumpy(np.array([p.min(axis=0) - pad, p.max(axis=0) + pad], dtype=np.float32))


def _author_guide(parent, node):
    gprim, shape = _guide_shape(node)
    # previews need no more digits than this, and rounding drops noise like 3.8e-17
    shape = {k: np.round(np.asarray(v, dtype=np.float64), 6) + 0.0 if k != "wrap" else v for k, v in shape.items()}
    spec = Sdf.PrimSpec(parent, _GUIDE, Sdf.SpecifierDef, gprim)
    _set(spec, "purpose", _T.Token, UsdGeom.Tokens.guide, uniform=True)
    if gprim in ("Sphere", "Cube"):
        ops = ["xformOp:translate"]
        _set(spec, ops[0], _T.Double3, Gf.Vec3d(*np.asarray(shape["translate"]).tolist()))
        if gprim == "Sphere":
            r = float(shape["radius"])
            _set(spec, "radius", _T.Double, r)
            _set(spec, "extent", _T.Float3Array, Vt.Vec3fArray([Gf.Vec3f(-r, -r, -r), Gf.Vec3f(r, r, r)]))
        else:  # the unit cube spans [-1, 1]^3 (its fallback extent)
            ops.append("xformOp:scale")
            _set(spec, ops[1], _T.Float3, Gf.Vec3f(*shape["scale"].tolist()))
        _set(spec, "xformOpOrder", _T.TokenArray, Vt.TokenArray(ops), uniform=True)
        return
    points = np.asarray(shape["points"], dtype=np.float64)
    _set(spec, "points", _T.Point3fArray, Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    if gprim == "Mesh":
        n = len(points)
        _set(spec, "faceVertexCounts", _T.IntArray, Vt.IntArray([n]))
        _set(spec, "faceVertexIndices", _T.IntArray, Vt.IntArray(list(range(n))))
        _set(spec, "doubleSided", _T.Bool, True, uniform=True)
        _set(spec, "extent", _T.Float3Array, _extent(points))
        return
    widths = np.asarray(shape["widths"], dtype=np.float32)
    _set(spec, "type", _T.Token, UsdGeom.Tokens.linear, uniform=True)
    if shape.get("wrap"):
        _set(spec, "wrap", _T.Token, UsdGeom.Tokens.periodic, uniform=True)
    _set(spec, "curveVertexCounts", _T.IntArray, Vt.IntArray([len(points)]))
    interpolation = UsdGeom.Tokens.constant if len(widths) == 1 else UsdGeom.Tokens.vertex
    _set(spec, "widths", _T.FloatArray, Vt.FloatArray.FromNumpy(widths), interpolation=interpolation)
    _set(spec, "extent", _T.Float3Array, _extent(points, 0.5 * float(widths.max())))


# ---------------------------------------------------------------------------
# reading
# ---------------------------------------------------------------------------


def load_model(path, prim_path=None) -> Node:
    """Read the BlobTree under ``prim_path`` of the USD file ``path``.

    The stage is composed first (references, inherits, payloads, variants).
    Transforms of the prim's ancestors are not part of the model; its own and
    its descendants' are. Coordinates are read as they are, whatever the
    stage's ``metersPerUnit`` and ``upAxis``.

    Args:
        path: a ``.usda``, ``.usdc``, ``.usd`` or ``.usdz`` file.
        prim_path: the model's root prim; default: the default prim, or the
            only root prim of a stage without one.

    Returns:
        The model (a new tree).

    Raises:
        SceneError: the file is missing or not USD, the prim is missing, or
            the scene is not a valid model; the message names the file, the
            prim and the attribute.
    """
    source = os.fspath(path)
    stage = open_stage(source, "load_model")
    prim = _root_prim(stage, source, prim_path)
    _check_composition(stage, source, prim.GetPath())
    return _Reader(source).read(prim)


def _one_line(err) -> str:
    """A USD or warpblob error as one short line: Tf's commentary, no anonymous session layers."""
    notes = [getattr(a, "commentary", None) for a in getattr(err, "args", ())]
    text = "; ".join(n for n in notes if n) or str(err)
    text = re.sub(r",@anon:[^@]*@", "", text)
    return " ".join(text.split())[:400]


def _root_prim(stage, source, prim_path):
    if prim_path is None:
        prim = stage.GetDefaultPrim()
        if not prim:
            roots = stage.GetPseudoRoot().GetChildren()
            if len(roots) != 1:
                raise SceneError(
                    f"{source}: the stage has no default prim and {len(roots)} root prims; pass prim_path"
                )
            prim = roots[0]
        return prim
    text = str(prim_path)
    if not Sdf.Path.IsValidPathString(text) or not Sdf.Path(text).IsAbsolutePath():
        raise SceneError(f"{source}: prim_path must be an absolute prim path, got {prim_path!r}")
    prim = stage.GetPrimAtPath(text)
    if not prim:
        raise SceneError(f"{source}: no prim <{text}>")
    return prim


def _check_composition(stage, source, root: Sdf.Path):
    """Composition errors in or above the model (reference cycles, missing assets) are fatal."""
    for err in stage.GetCompositionErrors():
        site = getattr(err, "rootSite", None)
        where = site.path if site is not None else root
        if where.HasPrefix(root) or root.HasPrefix(where):
            what = "reference cycle" if err.errorType == Pcp.ErrorType_ArcCycle else "composition error"
            raise SceneError(f"{source}: prim <{where}>: {what}: {_one_line(err)}")


_NODE_CHILDREN = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)


def _type_of(prim) -> str:
    return f"type {prim.GetTypeName()!r}" if prim.GetTypeName() else "an untyped prim"


@dataclass
class _PrimInfo:
    kind: _Kind
    params: dict
    operands: list
    color: np.ndarray | None
    matrix: np.ndarray | None


class _Reader:
    """Turns composed prims into nodes; every failure names the file, prim and attribute."""

    def __init__(self, source: str):
        self.source = source

    def error(self, prim, attr, text) -> SceneError:
        where = f"{self.source}: prim <{prim.GetPath()}>"
        return SceneError(f"{where}, attribute {attr}: {text}" if attr else f"{where}: {text}")

    def read(self, root) -> Node:
        built: dict = {}
        inherited = None  # colours are inherited like USD's constant primvars, from above the root too
        ancestor = root.GetParent()
        while inherited is None and ancestor and not ancestor.IsPseudoRoot():
            attr = ancestor.GetAttribute(_COLOR)
            if attr and attr.HasAuthoredValue():
                inherited = self.color(ancestor, attr)
            ancestor = ancestor.GetParent()
        # post-order without recursion: trees may be deeper than Python's stack
        stack = [(root, inherited, None)]
        while stack:
            prim, inherited, info = stack.pop()
            if info is None:
                info = self.read_prim(prim, inherited)
                stack.append((prim, inherited, info))
                stack.extend((c, info.color, None) for c in reversed(info.operands))
                continue
            children = [built.pop(c.GetPath()) for c in info.operands]
            built[prim.GetPath()] = self.build(prim, info, children)
        return built[root.GetPath()]

    # --- one prim ------------------------------------------------------------
    def read_prim(self, prim, inherited) -> _PrimInfo:
        props = {p.GetName(): p for p in prim.GetAuthoredPropertiesInNamespace(_NS)}
        kind_name = self.value(prim, props.get(_KIND), _KIND, _TOKEN)
        if kind_name is None:
            raise self.error(prim, _KIND, "missing (every node prim needs its kind token)")
        kind = _KINDS.get(kind_name)
        if kind is None:
            raise self.error(prim, _KIND, f"unknown kind {kind_name!r}; expected one of {', '.join(_KINDS)}")
        if not prim.IsA(UsdGeom.Xformable):
            raise self.error(prim, None, f"node prims must be Xform prims, got {_type_of(prim)}")
        known = {_KIND, _ORDER, _VERSION} | {p.attr for p in kind.params}
        unknown = sorted(set(props) - known)
        if unknown:
            raise self.error(
                prim, unknown[0], f"not an attribute of kind {kind_name!r}; it has {', '.join(sorted(known))}"
            )
        version = self.value(prim, props.get(_VERSION), _VERSION, _INT)
        if version is not None and not 1 <= version <= FORMAT_VERSION:
            raise self.error(
                prim, _VERSION, f"format version {version} is not supported (this reader knows 1 to {FORMAT_VERSION})"
            )
        params = {}
        for p in kind.params:
            v = self.value(prim, props.get(p.attr), p.attr, p.type)
            if v is None:
                if p.default is None:
                    raise self.error(prim, p.attr, f"missing (required {p.type.name} for kind {kind_name!r})")
                v = p.default
            params[p.name] = v
        color = inherited
        color_attr = prim.GetAttribute(_COLOR)
        if color_attr and color_attr.HasAuthoredValue():
            color = self.color(prim, color_attr)
        return _PrimInfo(kind, params, self.operands(prim, kind_name, kind), color, self.transform(prim))

    def value(self, prim, prop, name, typ):
        """The default-time value of ``prop`` checked against ``typ``; None if absent."""
        if prop is None:
            return None
        if not isinstance(prop, Usd.Attribute):
            raise self.error(prim, name, "must be an attribute, found a relationship")
        type_name = prop.GetTypeName()
        if type_name.type not in typ.accepts:
            raise self.error(prim, name, f"must be {typ.name}, got {type_name} {prop.Get()!r}")
        v = prop.Get()
        if v is None:
            return None
        if typ.shape is None:
            return str(v) if typ is _TOKEN else int(v)
        arr = np.array(v, dtype=np.float64)
        if typ.shape == ():
            return float(arr)
        if typ.shape[0] is None and arr.size == 0:
            arr = arr.reshape(0, typ.shape[1])
        return arr

    def color(self, prim, attr):
        if attr.GetTypeName().type not in _DOUBLE3_ARRAY.accepts:
            raise self.error(prim, _COLOR, f"must be color3f[], got {attr.GetTypeName()}")
        values = np.array(attr.Get(), dtype=np.float64).reshape(-1, 3)
        if len(values) == 0:
            raise self.error(prim, _COLOR, "is empty; it needs one colour")
        return values[0]

    def operands(self, prim, kind_name, kind) -> list:
        """Child prims with ``warpblob:`` attributes, sorted by ``warpblob:order``."""
        ordered = []
        for child in prim.GetFilteredChildren(_NODE_CHILDREN):
            props = child.GetAuthoredPropertiesInNamespace(_NS)
            if not props:
                continue  # a guide, or a DCC tool's own prim
            order = self.value(child, child.GetProperty(_ORDER) or None, _ORDER, _INT)
            if order is None:
                raise self.error(child, _ORDER, "missing (every operand prim needs its int order)")
            ordered.append((order, child))
        ordered.sort(key=lambda oc: oc[0])
        for (o1, c1), (o2, c2) in zip(ordered, ordered[1:]):
            if o1 == o2:
                raise self.error(c2, _ORDER, f"{o2} is also the order of <{c1.GetPath()}>")
        n = len(ordered)
        lo, hi = kind.min_operands, kind.max_operands
        if n < lo or (hi is not None and n > hi):
            if hi == 0:
                wanted = "no operands (a primitive)"
            elif hi == lo:
                wanted = f"exactly {lo} operand{'s' if lo > 1 else ''}"
            else:
                wanted = f"at least {lo} operand{'s' if lo > 1 else ''}"
            found = ", ".join(f"<{c.GetPath()}>" for _, c in ordered) or "none"
            raise self.error(prim, None, f"kind {kind_name!r} takes {wanted}, found {n} ({found})")
        return [c for _, c in ordered]

    def transform(self, prim):
        """The prim's local matrix (column-vector convention), or None if it has no xformOps.

        An identity xformOp still gives a matrix, so identity Transform nodes survive a round trip.
        """
        xformable = UsdGeom.Xformable(prim)
        try:
            if xformable.GetResetXformStack():
                raise self.error(prim, "xformOpOrder", "!resetXformStack! cannot be part of a model")
            if not xformable.GetOrderedXformOps():
                return None
            local = xformable.GetLocalTransformation()
        except Tf.ErrorException as err:
            raise self.error(prim, "xformOpOrder", _one_line(err)) from None
        return np.array(local, dtype=np.float64).T

    def build(self, prim, info: _PrimInfo, children) -> Node:
        kind, params = info.kind, dict(info.params)
        try:
            if "sketch" in params:
                try:
                    params["sketch"] = Sketch(params["sketch"])
                except ModelError as err:
                    raise self.error(prim, f"{_NS}:sketch", _one_line(err)) from None
            if kind.is_primitive:
                node = kind.cls(**params, color=DEFAULT_COLOR if info.color is None else info.color)
            else:
                node = kind.cls(*children, **params)
        except ModelError as err:
            raise self.error(prim, self.blame(kind, str(err)), _one_line(err)) from None
        if info.matrix is not None:
            try:
                node = Transform(node, info.matrix)
            except ModelError as err:
                raise self.error(prim, "xformOpOrder", _one_line(err)) from None
        return node

    @staticmethod
    def blame(kind: _Kind, message: str) -> str:
        """The attribute a constructor's ModelError is about: it starts "Cls: name ...".

        When the first word names no parameter, every parameter of the kind is named.
        """
        words = message.split(": ", 1)[-1].split()
        word = words[0] if words else ""
        names = [p.name for p in kind.params]
        if word == "color":
            return _COLOR
        if word in names:
            return f"{_NS}:{word}"
        if kind.cls is Triangle and word == "points":  # a Triangle validates its corners as a Polygon
            names = ["p0", "p1", "p2"]
        return ", ".join(f"{_NS}:{n}" for n in names)
