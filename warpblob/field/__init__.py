"""The field engine: Warp kernels evaluating linearized BlobTrees."""

from ._engine import bound_balls, bound_blocks, color, evaluate, field, gradient, grid_field

__all__ = ["field", "gradient", "color", "evaluate", "bound_balls", "bound_blocks", "grid_field"]
