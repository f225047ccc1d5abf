"""The field engine: Warp kernels evaluating linearized BlobTrees."""

from ._engine import color, evaluate, field, gradient

__all__ = ["field", "gradient", "color", "evaluate"]
