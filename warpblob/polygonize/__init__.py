"""Polygonization: BlobTree to watertight, coloured, shared-vertex triangle mesh."""

from ._pipeline import available_memory, polygonize

__all__ = ["polygonize", "available_memory"]
