"""USD files: BlobTree models (``save_model``, ``load_model``), meshes (``save_mesh``, ``load_mesh``,
``save_tetmesh``, ``load_tetmesh``), animated stages (:class:`Recorder`; the readers take a ``time``) and their
pictures (:func:`render_gif`).

``import warpblob.usd`` loads Pixar's ``pxr``; ``import warpblob`` does not.
The mesh types are data: :mod:`warpblob.mesh` never imports this module.
The model file format is described in ``docs/usd_format.md``, recordings in ``docs/usd.md``.

Example:
    >>> import os, tempfile
    >>> import warpblob as wb
    >>> import warpblob.usd
    >>> path = wb.usd.save_model(wb.scenes.tumor(), os.path.join(tempfile.mkdtemp(), "tumor.usda"))
    >>> wb.usd.load_model(path).primitive_count()
    10
"""

import os

from ._errors import SceneError
from .io._movie import render_frames, render_gif, stage_summary
from .io._recorder import Recorder, load_mesh_at, load_tetmesh_at
from .io.usd import FORMAT_VERSION, METERS_PER_UNIT, load_model, save_mesh, save_model, save_tetmesh
from .io.usd import load_mesh as _load_mesh

__all__ = ["save_model", "load_model", "save_mesh", "load_mesh", "save_tetmesh", "load_tetmesh", "Recorder",
           "render_gif", "render_frames", "stage_summary", "FORMAT_VERSION", "METERS_PER_UNIT"]  # fmt: skip


def load_mesh(path, prim_path: str | None = None, *, time: float | None = None):
    """A :class:`~warpblob.mesh.SurfaceMesh` from a USD file; at time code ``time`` of an animated stage if given.

    Without ``time``, a Mesh prim (``prim_path``, else the default prim) is
    read as it is; any other prim (a recording's ``/World``) is read at its
    first time sample, every visible Mesh under it joined
    (:func:`warpblob.io._recorder.load_mesh_at`).

    Example:
        >>> import os, tempfile
        >>> import warpblob as wb
        >>> import warpblob.usd
        >>> mesh = wb.polygonize(wb.scenes.peanut(), cellsize=0.2)
        >>> wb.usd.load_mesh(wb.usd.save_mesh(mesh, os.path.join(tempfile.mkdtemp(), "p.usda"))).face_count > 0
        True
    """
    if time is None and _is_mesh(path, prim_path):
        return _load_mesh(path, prim_path)
    return load_mesh_at(path, prim_path, time=time)


def _is_mesh(path, prim_path) -> bool:
    from pxr import UsdGeom

    from .io.usd import _root_prim, open_stage

    source = os.fspath(path)
    stage = open_stage(source, "load_mesh")
    try:
        return _root_prim(stage, source, prim_path).IsA(UsdGeom.Mesh)
    except SceneError:  # a stage without a default prim: the time reader searches
        return False


def load_tetmesh(path, prim_path: str | None = None, *, time: float | None = None):
    """The :class:`~warpblob.mesh.TetMesh` of a USD file (``UsdGeom.TetMesh``), at time code ``time`` if given.

    The prim: ``prim_path``, else the first TetMesh under the default prim (or
    on the stage). Without ``time`` the default value, else the first sample,
    is read. See :func:`warpblob.io._recorder.load_tetmesh_at`.

    Raises:
        SceneError: the file is missing or not USD, holds no such TetMesh, or
            its arrays do not make a valid TetMesh; the message names the file.

    Example:
        >>> import os, tempfile
        >>> import warpblob as wb
        >>> import warpblob.usd
        >>> mesh = wb.mesh.box_tetmesh((0, 0, 0), (1, 1, 1), (2, 2, 2))
        >>> path = wb.usd.save_tetmesh(mesh, os.path.join(tempfile.mkdtemp(), "box.usdc"), prim_path="/World/Box")
        >>> wb.usd.load_tetmesh(path, "/World/Box").tet_count
        48
    """
    return load_tetmesh_at(path, prim_path, time=time)
