"""The BlobTree node base class, bounding boxes and affine transforms.

A model is an immutable tree of nodes. Every node maps a point of its parent's
frame to a field value ``F >= 0`` that is exactly 0 outside ``node.bounds()``;
the iso-surface is ``F = 0.5`` (Wyvill, Guy & Galin 1999, "Extending the CSG
tree").
"""

from __future__ import annotations

import numpy as np

from .._errors import ModelError
from . import _check

__all__ = ["Node", "Transform", "ISO_VALUE"]

#: The iso-value of every warpblob model: inside is ``F >= ISO_VALUE``.
ISO_VALUE = 0.5

#: Relative padding of primitive boxes (fraction of the support radius) so that
#: float32 rounding can never put a non-zero field value outside a box.
BOX_PAD = 1e-3


def empty_box() -> tuple[np.ndarray, np.ndarray]:
    """A box that contains no point (lower > upper)."""
    return np.full(3, np.inf), np.full(3, -np.inf)


def box_is_empty(box) -> bool:
    lower, upper = box
    return bool(np.any(lower > upper))


def box_union(boxes) -> tuple[np.ndarray, np.ndarray]:
    """Smallest box containing every non-empty box of ``boxes``."""
    lower, upper = empty_box()
    for lo, hi in boxes:
        if np.all(lo <= hi):
            lower = np.minimum(lower, lo)
            upper = np.maximum(upper, hi)
    return lower, upper


def box_intersection(boxes) -> tuple[np.ndarray, np.ndarray]:
    """Intersection of ``boxes`` (empty when they do not overlap)."""
    lower = np.full(3, -np.inf)
    upper = np.full(3, np.inf)
    for lo, hi in boxes:
        lower = np.maximum(lower, lo)
        upper = np.minimum(upper, hi)
    if np.any(lower > upper):
        return empty_box()
    return lower, upper


def box_transform(matrix: np.ndarray, box) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box of the image of ``box`` under the affine 4x4 ``matrix``."""
    if box_is_empty(box):
        return empty_box()
    lower, upper = box
    center = 0.5 * (lower + upper)
    half = 0.5 * (upper - lower)
    lin = matrix[:3, :3]
    new_center = lin @ center + matrix[:3, 3]
    new_half = np.abs(lin) @ half
    return new_center - new_half, new_center + new_half


def rotation_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` radians about the unit vector ``axis`` (right hand)."""
    x, y, z = axis
    c, s = np.cos(angle), np.sin(angle)
    t = 1.0 - c
    return np.array(
        [
            [t * x * x + c, t * x * y - s * z, t * x * z + s * y],
            [t * x * y + s * z, t * y * y + c, t * y * z - s * x],
            [t * x * z - s * y, t * y * z + s * x, t * z * z + c],
        ]
    )


def frame_matrix(origin, z_axis, x_hint=None) -> np.ndarray:
    """Rigid 4x4 local-to-parent matrix with its z axis along ``z_axis`` (unit)."""
    z = np.asarray(z_axis, dtype=np.float64)
    if x_hint is None:
        x_hint = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = x_hint - np.dot(x_hint, z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, origin
    return m


class Node:
    """Base class of every BlobTree node (primitive, operator, warp, transform).

    Nodes are immutable: operators and methods return new nodes.

    Operators: ``a + b`` blend (sum), ``a | b`` union (max), ``a & b``
    intersection (min), ``a - b`` difference.
    Transforms: ``node.translate(v)``, ``node.rotate(axis, angle)``,
    ``node.scale(s)``; each returns a :class:`Transform` (consecutive
    transforms are merged into one node).

    Example:
        >>> import warpblob as wb
        >>> m = (wb.Point((0, 0, 0), 1.0) + wb.Point((0.8, 0, 0), 1.0)).translate((0, 0, 1))
        >>> m.primitive_count(), m.operator_count()
        (2, 2)
    """

    #: kind name used by the linearizer, the USD format and error messages
    kind: str = "node"

    def __init__(self, children=()):
        self._children = tuple(children)
        for c in self._children:
            if not isinstance(c, Node):
                raise ModelError(f"{type(self).__name__}: operand must be a warpblob Node, got {c!r}")
        self._bounds = None

    @property
    def children(self) -> tuple["Node", ...]:
        """The operands of this node, in order (empty for primitives)."""
        return self._children

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lower, upper)`` float64 arrays of shape (3,), in the parent frame.

        The field of the node is exactly 0 outside this box.
        """
        if self._bounds is None:
            self._bounds = self._compute_bounds()
        lower, upper = self._bounds
        return lower.copy(), upper.copy()

    def _compute_bounds(self):  # pragma: no cover - abstract
        raise NotImplementedError

    # --- counts -----------------------------------------------------------
    def primitive_count(self) -> int:
        """Number of primitive leaves."""
        return sum(1 for n in self.walk() if not n.children)

    def operator_count(self) -> int:
        """Number of inner nodes: operators, warps and transform nodes."""
        return sum(1 for n in self.walk() if n.children)

    def depth(self) -> int:
        """Nodes on the longest root-to-leaf path.

        Transform nodes are folded into the leaves by :func:`warpblob.linearize`
        and add no level; a lone primitive has depth 1.
        """
        stack = [(self, 1)]
        best = 0
        while stack:
            node, d = stack.pop()
            if isinstance(node, Transform):
                stack.append((node.child, d))
            elif node.children:
                stack.extend((c, d + 1) for c in node.children)
            else:
                best = max(best, d)
        return best

    def walk(self):
        """Yield every node of the tree in pre-order (iteratively)."""
        stack = [self]
        while stack:
            node = stack.pop()
            yield node
            stack.extend(reversed(node.children))

    # --- operators --------------------------------------------------------
    def __add__(self, other):
        from ._operators import Blend

        return Blend(*_flatten(Blend, self, other))

    def __or__(self, other):
        from ._operators import Union

        return Union(*_flatten(Union, self, other))

    def __and__(self, other):
        from ._operators import Intersection

        return Intersection(*_flatten(Intersection, self, other))

    def __sub__(self, other):
        from ._operators import Difference

        return Difference(self, other)

    # --- transforms -------------------------------------------------------
    def transform(self, matrix) -> "Transform":
        """Apply the affine 4x4 ``matrix``: the result at ``p`` is ``self`` at ``M^-1 p``."""
        return Transform(self, matrix)

    def translate(self, offset) -> "Transform":
        """Move the node by ``offset`` (3,)."""
        m = np.eye(4)
        m[:3, 3] = _check.vector("translate", "offset", offset)
        return Transform(self, m)

    def rotate(self, axis, angle: float) -> "Transform":
        """Rotate the node by ``angle`` radians about ``axis`` through the origin."""
        a = _check.direction("rotate", "axis", axis)
        m = np.eye(4)
        m[:3, :3] = rotation_matrix(a, _check.scalar("rotate", "angle", angle))
        return Transform(self, m)

    def scale(self, factor) -> "Transform":
        """Scale the node about the origin by a scalar or a per-axis (3,) factor."""
        f = np.atleast_1d(np.asarray(factor, dtype=np.float64))
        if f.shape == (1,):
            f = np.repeat(f, 3)
        f = _check.vector("scale", "factor", f)
        if np.any(np.abs(f) < 1e-12):
            raise ModelError(f"scale: factor must be non-zero on every axis, got {factor!r}")
        return Transform(self, np.diag([*f, 1.0]))

    def __repr__(self):
        return f"{type(self).__name__}({len(self.children)} children)" if self.children else type(self).__name__


def _flatten(cls, a, b):
    parts = []
    for x in (a, b):
        if type(x) is cls:
            parts.extend(x.children)
        else:
            parts.append(x)
    return parts


class Transform(Node):
    """Affine transform of a subtree: the child is evaluated at ``M^-1 p``.

    Args:
        child: the transformed subtree.
        matrix: (4, 4) affine matrix (last row 0, 0, 0, 1), invertible.

    Bounds: the axis-aligned box of the child's box mapped by ``M``.
    """

    kind = "transform"

    def __init__(self, child: Node, matrix):
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ModelError(f"Transform: matrix must be a finite 4x4 array, got {matrix!r}")
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]):
            raise ModelError(f"Transform: matrix last row must be (0, 0, 0, 1), got {m[3]!r}")
        if abs(np.linalg.det(m[:3, :3])) < 1e-12:
            raise ModelError(f"Transform: matrix must be invertible, got {matrix!r}")
        if isinstance(child, Transform):
            m = m @ child.matrix
            child = child.child
        super().__init__((child,))
        self._matrix = m

    @property
    def child(self) -> Node:
        return self.children[0]

    @property
    def matrix(self) -> np.ndarray:
        """The (4, 4) child-to-parent matrix."""
        return self._matrix.copy()

    def _compute_bounds(self):
        return box_transform(self._matrix, self.child.bounds())
