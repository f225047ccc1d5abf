"""The field engine: Warp kernels evaluating linearized BlobTrees."""

from ._engine import bound_balls, color, evaluate, field, gradient, grid_field

__all__ = ["field", "gradient", "color", "evaluate", "bound_balls", "grid_field"]
