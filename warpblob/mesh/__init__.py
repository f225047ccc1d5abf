"""Mesh types: triangle surfaces (and, later, tetrahedral meshes)."""

from ._surface import SurfaceMesh

__all__ = ["SurfaceMesh"]
