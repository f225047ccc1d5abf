"""Exception types raised by warpblob at its Python boundary."""

__all__ = ["WarpblobError", "ModelError", "SceneError", "ResourceError"]


class WarpblobError(Exception):
    """Base class of every error warpblob raises on purpose."""


class ModelError(WarpblobError, ValueError):
    """A model (primitive, operator, warp or transform) got a bad parameter."""


class SceneError(WarpblobError, ValueError):
    """A scene file could not be read (or written: a bad path or prim path)."""


class ResourceError(WarpblobError, MemoryError):
    """A request would need more memory than is available."""
