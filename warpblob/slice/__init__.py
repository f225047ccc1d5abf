"""Planar slicing and capping of closed triangle meshes (a saw cut), see :func:`slice`."""

from ._slice import CAP_COLOR, SNAP, slice

__all__ = ["slice", "SNAP", "CAP_COLOR"]
