"""Exception types raised by warpblob at its Python boundary."""

__all__ = ["WarpblobError", "ModelError", "SceneError", "ResourceError", "MeshError", "SimulationError", "ToolError", "CutError"]


class WarpblobError(Exception):
    """Base class of every error warpblob raises on purpose."""


class ModelError(WarpblobError, ValueError):
    """A model (primitive, operator, warp or transform) got a bad parameter."""


class SceneError(WarpblobError, ValueError):
    """A scene file could not be read (or written: a bad path or prim path)."""


class ResourceError(WarpblobError, MemoryError):
    """A request would need more memory than is available."""


class MeshError(WarpblobError, ValueError):
    """A mesh is not what an operation needs (open, non-manifold, inverted, wrong shapes)."""


class SimulationError(WarpblobError, ValueError):
    """A simulation got a bad parameter or mesh, or a step diverged."""


class ToolError(WarpblobError, ValueError):
    """A tool or tool path got a bad parameter (non-increasing times, NaN poses, an open mesh)."""


class CutError(WarpblobError, ValueError):
    """A cut got a bad sweep, tool path or mesh (NaN points, too few samples, wrong shapes)."""
