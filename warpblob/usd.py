"""USD files: BlobTree models (``save_model``, ``load_model``) and surface meshes (``save_mesh``, ``load_mesh``).

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

from .io.usd import FORMAT_VERSION, METERS_PER_UNIT, load_mesh, load_model, save_mesh, save_model

__all__ = ["save_model", "load_model", "save_mesh", "load_mesh", "FORMAT_VERSION", "METERS_PER_UNIT"]
