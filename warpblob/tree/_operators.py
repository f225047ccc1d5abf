"""Operators of the BlobTree (Wyvill, Guy & Galin 1999) and space warps (Barr 1984).

Every field here is >= 0 and exactly 0 outside the node's box:

==================  ========================================  =============================
operator            field                                     box
==================  ========================================  =============================
Blend(*c)           sum F_i                                   union of the children's boxes
Union(*c)           max F_i                                   union of the children's boxes
Intersection(*c)    min F_i                                   intersection of the boxes
Difference(a, b)    min(F_a, 1 - min(F_b, 1))                 box of a
SmoothBlend(*c, k)  (sum F_i^k)^(1/k)                         union of the children's boxes
==================  ========================================  =============================

Difference clamps ``F_b`` at 1 so that the field never goes negative (a
blend inside ``b`` can exceed 1); the iso-surface ``F = 0.5`` is that of
``min(F_a, 1 - F_b)``.

Colours: a blend (and a smooth blend, weighted by ``F_i^k``) takes the
field-weighted mean of its children's colours; union, intersection and
difference take the colour of the child that decides the value (exact ties
go to the operand evaluated first, which the linearizer may reorder; a difference whose ``F_b`` is 0 keeps ``a``'s colour even
where ``F_a > 1`` is clamped to 1). Where a field is 0 its colour is defined
as black.
"""

from __future__ import annotations

import numpy as np

from .._errors import ModelError
from . import _check, _kinds
from ._node import Node, box_intersection, box_union

__all__ = [
    "Operator",
    "Blend",
    "Union",
    "Intersection",
    "Difference",
    "SmoothBlend",
    "Warp",
    "Twist",
    "Taper",
    "Bend",
]


class Operator(Node):
    """An n-ary operator node."""

    code: int = -1
    min_children = 1

    def __init__(self, *children):
        name = type(self).__name__
        if len(children) == 1 and isinstance(children[0], (list, tuple)):
            children = tuple(children[0])
        if len(children) < self.min_children:
            raise ModelError(
                f"{name}: needs at least {self.min_children} operand(s), got {len(children)}"
            )
        super().__init__(children)

    def params(self) -> np.ndarray:
        return np.zeros(4)


class Blend(Operator):
    """Summation blend ``F = sum F_i`` (``a + b``).

    Example:
        >>> import warpblob as wb
        >>> peanut = wb.Blend(wb.Point((-0.4, 0, 0), 1.0), wb.Point((0.4, 0, 0), 1.0))
        >>> peanut.primitive_count()
        2
    """

    kind = "blend"
    code = _kinds.BLEND

    def _compute_bounds(self):
        return box_union(c.bounds() for c in self.children)


class Union(Blend):
    """CSG union ``F = max F_i`` (``a | b``)."""

    kind = "union"
    code = _kinds.UNION


class SmoothBlend(Blend):
    """Smooth (Ricci) blend ``F = (sum F_i^k)^(1/k)``.

    ``k = 1`` is the summation blend, ``k -> inf`` the union.

    Args:
        children: two or more operands.
        k: blend exponent, ``k >= 1``.
    """

    kind = "smooth_blend"
    code = _kinds.SMOOTH_BLEND
    min_children = 2

    def __init__(self, *children, k: float = 2.0):
        super().__init__(*children)
        self.k = _check.scalar("SmoothBlend", "k", k)
        if self.k < 1.0:
            raise ModelError(f"SmoothBlend: k must be >= 1, got {k!r}")

    def params(self):
        return np.array([self.k, 0.0, 0.0, 0.0])


class Intersection(Operator):
    """CSG intersection ``F = min F_i`` (``a & b``)."""

    kind = "intersection"
    code = _kinds.INTERSECTION

    def _compute_bounds(self):
        return box_intersection(c.bounds() for c in self.children)


class Difference(Operator):
    """CSG difference ``F = min(F_a, 1 - min(F_b, 1))`` (``a - b``): ``a`` with ``b`` cut away."""

    kind = "difference"
    code = _kinds.DIFFERENCE
    min_children = 2

    def __init__(self, *operands: Node):
        if len(operands) != 2:
            raise ModelError(f"Difference: needs exactly 2 operands (a, b), got {len(operands)}")
        super().__init__(*operands)

    def _compute_bounds(self):
        return self.children[0].bounds()


class Warp(Operator):
    """A space warp of one subtree: the child is evaluated at ``W(p)``.

    ``axis`` passes through the origin of the warp's frame; place a warp with
    ``.translate`` / ``.rotate`` like any node.
    """

    def __init__(self, child: Node):
        super().__init__(child)

    @property
    def child(self) -> Node:
        return self.children[0]

    def _compute_bounds(self):
        return self._warp_box(self.child.bounds())


def _axial_radial_extent(box, axis):
    """Range of ``p . axis`` and the largest distance to the axis line over ``box``."""
    lo, hi = box
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    t = corners @ axis
    radial = np.linalg.norm(corners - np.outer(t, axis), axis=1)
    return float(t.min()), float(t.max()), float(radial.max())


def _cylinder_box(axis, t0, t1, r):
    """Box of the solid cylinder of radius ``r`` around ``axis`` for ``p . axis`` in [t0, t1]."""
    ends = np.array([t0 * axis, t1 * axis])
    ext = r * np.sqrt(np.clip(1.0 - axis * axis, 0.0, 1.0))
    return ends.min(axis=0) - ext, ends.max(axis=0) + ext


class Twist(Warp):
    """Twist about ``axis``: the child is evaluated at ``p`` rotated about ``axis``
    (through the origin) by ``-rate * (p . axis)`` radians.

    Args:
        child: the warped subtree.
        axis: (3,) twist axis (normalized).
        rate: radians per model unit along the axis.

    Bounds: the cylinder around the axis that holds the child's box, boxed.
    """

    kind = "twist"
    code = _kinds.TWIST

    def __init__(self, child: Node, axis, rate: float):
        super().__init__(child)
        self.axis = _check.direction("Twist", "axis", axis)
        self.rate = _check.scalar("Twist", "rate", rate)

    def params(self):
        return np.array([*self.axis, self.rate])

    def _warp_box(self, box):
        t0, t1, r = _axial_radial_extent(box, self.axis)
        return _cylinder_box(self.axis, t0, t1, r)


class Taper(Warp):
    """Taper along ``axis``: coordinates perpendicular to ``axis`` are divided by
    ``1 + slope * (p . axis)``.

    The scale ``1 + slope * t`` must stay above 0.05 over the child's box
    (otherwise the warp folds space), else ModelError.

    Bounds: the cylinder around the axis holding the child's box, its radius
    multiplied by the largest scale over the axial range.
    """

    kind = "taper"
    code = _kinds.TAPER

    def __init__(self, child: Node, axis, slope: float):
        super().__init__(child)
        self.axis = _check.direction("Taper", "axis", axis)
        self.slope = _check.scalar("Taper", "slope", slope)
        t0, t1, _ = _axial_radial_extent(child.bounds(), self.axis)
        smallest = min(1.0 + self.slope * t0, 1.0 + self.slope * t1)
        if smallest < 0.05:
            raise ModelError(
                f"Taper: slope {slope!r} makes the scale 1 + slope*t fall to {smallest:.3g} "
                f"over the child's axial range [{t0:.3g}, {t1:.3g}]; it must stay above 0.05"
            )

    def params(self):
        return np.array([*self.axis, self.slope])

    def _warp_box(self, box):
        t0, t1, r = _axial_radial_extent(box, self.axis)
        scale = max(1.0 + self.slope * t0, 1.0 + self.slope * t1)
        return _cylinder_box(self.axis, t0, t1, r * scale)


class Bend(Warp):
    """Circular bend: the line through the origin along ``direction`` is bent
    into a circle of radius ``1 / rate`` towards ``up``.

    With ``x = p . d``, ``y = p . u``, ``z = p . (d x u)``, ``rho = 1 / rate``,
    ``theta = atan2(x, rho - y)`` and ``r = |(x, rho - y)|``, the child is
    evaluated at ``q = rho * theta * d + (rho - r) * u + z * (d x u)``.
    Along the bent axis distances are preserved (an isometry at ``y = 0``).
    A negative rate bends towards ``-up``. The child's box must stay within
    ``|x| < pi * |rho|`` and on the near side of the bend centre, else ModelError.

    Args:
        child: the bent subtree.
        direction: (3,) the axis that gets bent.
        up: (3,) the side the bend turns to (made orthogonal to ``direction``).
        rate: curvature, 1 / model unit, non-zero.

    Bounds: the box of the annular sector that the child's box maps to.
    """

    kind = "bend"
    code = _kinds.BEND

    def __init__(self, child: Node, direction=(1.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), rate: float = 0.5):
        super().__init__(child)
        d = _check.direction("Bend", "direction", direction)
        u = _check.vector("Bend", "up", up)
        u = u - np.dot(u, d) * d
        if np.linalg.norm(u) < 1e-9:
            raise ModelError(f"Bend: up must not be parallel to direction, got up={up!r}")
        self.rate = _check.scalar("Bend", "rate", rate)
        if self.rate == 0.0:
            raise ModelError("Bend: rate must be non-zero (leave the Bend out for no bend), got 0")
        self.direction, self.up = d, u / np.linalg.norm(u)
        # the kernel bends towards ``side`` with a positive radius
        self.side = self.up if self.rate > 0.0 else -self.up
        self.rho = 1.0 / abs(self.rate)
        lo, hi = self._local_box(child.bounds())
        if max(abs(lo[0]), abs(hi[0])) >= np.pi * self.rho or hi[1] >= self.rho:
            raise ModelError(
                f"Bend: rate {rate!r} wraps the child (its box spans x in [{lo[0]:.3g}, {hi[0]:.3g}], "
                f"y up to {hi[1]:.3g}; bend radius {self.rho:.3g})"
            )

    def _basis(self):
        return np.array([self.direction, self.side, np.cross(self.direction, self.side)])

    def _local_box(self, box):
        lo, hi = box
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        loc = corners @ self._basis().T
        return loc.min(axis=0), loc.max(axis=0)

    def params(self):
        return np.array([*self.direction, self.rho])

    def data(self):
        return self.side.copy()

    def _warp_box(self, box):
        lo, hi = self._local_box(box)  # conservative box of the child in (x, y, z) bend coordinates
        rho = self.rho
        th0, th1 = lo[0] / rho, hi[0] / rho
        r0, r1 = rho - hi[1], rho - lo[1]
        thetas = [th0, th1] + [a for a in (-np.pi / 2, 0.0, np.pi / 2) if th0 < a < th1]
        xs, ys = [], []
        for th in thetas:
            for r in (r0, r1):
                xs.append(r * np.sin(th))
                ys.append(rho - r * np.cos(th))
        x0, x1, y0, y1 = min(xs), max(xs), min(ys), max(ys)
        corners = np.array(
            [[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (lo[2], hi[2])]
        ) @ self._basis()
        return corners.min(axis=0), corners.max(axis=0)
