"""Mesh types: triangle surfaces, tetrahedral meshes, their quality, and the
edge-based tetrahedral structure that simulation and cutting edit."""

from ._grid import box_tetmesh
from ._quality import TetQuality, format_quality, quality
from ._structure import (
    CellView,
    EdgeView,
    FaceView,
    NodeView,
    TetStructure,
    TetStructureArrays,
    edge_key,
    edge_table_find,
    lookup_edge,
)
from ._surface import SurfaceMesh
from ._tetmesh import TET_EDGES, TET_FACES, TetMesh

__all__ = [
    "SurfaceMesh",
    "TetMesh",
    "box_tetmesh",
    "TET_FACES",
    "TET_EDGES",
    "TetQuality",
    "quality",
    "format_quality",
    "TetStructure",
    "TetStructureArrays",
    "NodeView",
    "EdgeView",
    "FaceView",
    "CellView",
    "edge_key",
    "edge_table_find",
    "lookup_edge",
]
