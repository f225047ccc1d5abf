"""Device resolution shared by every layer (field, meshing, mesh data, simulation)."""

from __future__ import annotations

import warp as wp

from ._errors import WarpblobError

__all__ = ["resolve_device"]


def resolve_device(device) -> wp.context.Device:
    """The Warp device for ``device`` (name, Device or None), or WarpblobError."""
    try:
        return wp.get_device(device)
    except (ValueError, RuntimeError, TypeError) as exc:
        raise WarpblobError(f"device {device!r} is not available: {exc}") from None
