"""The field engine: Warp kernels evaluating linearized BlobTrees."""

from ._engine import bound_balls, bound_blocks, color, evaluate, field, gradient, grid_field
from ._volume import VolumeEstimate, monte_carlo_volume

__all__ = ["field", "gradient", "color", "evaluate", "bound_balls", "bound_blocks", "grid_field", "monte_carlo_volume", "VolumeEstimate"]
