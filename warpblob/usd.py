"""USD files: BlobTree models (``save_model``, ``load_model``), surface meshes (``save_mesh``, ``load_mesh``) and
animated stages (``Recorder``; ``load_tetmesh`` and ``load_mesh`` at a time code).

``import warpblob.usd`` loads Pixar's ``pxr``; ``import warpblob`` does not.
The file format is described in ``docs/usd_format.md``.

Example:
    >>> import os, tempfile
    >>> import warpblob as wb
    >>> import warpblob.usd
    >>> path = wb.usd.save_model(wb.scenes.tumor(), os.path.join(tempfile.mkdtemp(), "tumor.usda"))
    >>> wb.usd.load_model(path).primitive_count()
    10
"""

from .io._recorder import Recorder, load_mesh_at, load_tetmesh
from .io.usd import FORMAT_VERSION, METERS_PER_UNIT, load_model, save_mesh, save_model
from .io.usd import load_mesh as _load_mesh

__all__ = ["save_model", "load_model", "save_mesh", "load_mesh", "load_tetmesh", "Recorder", "FORMAT_VERSION",
           "METERS_PER_UNIT"]  # fmt: skip


def load_mesh(path, prim_path: str | None = None, *, time: float | None = None):
    """A :class:`~warpblob.mesh.SurfaceMesh` from a USD file; at time code ``time`` of an animated stage if given.

    Example:
        >>> import os, tempfile
        >>> import warpblob as wb
        >>> import warpblob.usd
        >>> mesh = wb.polygonize(wb.scenes.peanut(), cellsize=0.2)
        >>> wb.usd.load_mesh(wb.usd.save_mesh(mesh, os.path.join(tempfile.mkdtemp(), "p.usda"))).face_count > 0
        True
    """
    if time is None:
        return _load_mesh(path, prim_path)
    return load_mesh_at(path, time=time, prim_path=prim_path)
