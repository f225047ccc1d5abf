"""Skeletal primitives with the Wyvill falloff (Wyvill, McPheeters & Wyvill 1986).

The field of a primitive is ``f(p) = g(d(p, S) / R)`` with
``g(x) = (1 - x^2)^3`` on [0, 1), 1 below 0 and 0 from 1 on; ``d`` is the
Euclidean distance to the *solid* skeleton ``S`` and ``R`` the support radius.
A lone primitive's surface (F = 0.5) lies at ``d = 0.4541 R``.

Each primitive is described by a canonical skeleton in a local frame (for
example a segment from the origin along +x) and a rigid local-to-parent
``frame`` matrix; the kernels evaluate the canonical skeleton.
"""

from __future__ import annotations

import numpy as np

from .._errors import ModelError
from . import _check, _kinds
from ._node import BOX_PAD, Node, box_transform, frame_matrix

__all__ = [
    "Primitive",
    "Point",
    "Segment",
    "Disc",
    "Ring",
    "Cylinder",
    "Cone",
    "Triangle",
    "Polygon",
    "Box",
    "falloff",
    "ISO_DISTANCE",
]

#: Normalized distance of a lone primitive's iso-surface: sqrt(1 - 0.5^(1/3)).
ISO_DISTANCE = float(np.sqrt(1.0 - 0.5 ** (1.0 / 3.0)))

DEFAULT_COLOR = (0.8, 0.45, 0.4)


def falloff(x):
    """The Wyvill falloff ``g(x)`` (numpy, elementwise)."""
    x = np.asarray(x, dtype=np.float64)
    t = np.clip(1.0 - x * x, 0.0, 1.0)
    return np.where(x <= 0.0, 1.0, np.where(x >= 1.0, 0.0, t**3))


class Primitive(Node):
    """A leaf of the tree: a skeleton, a support radius and a colour.

    Attributes:
        radius: support radius ``R`` (model units); the field is 0 beyond it.
        color: RGB in [0, 1], shape (3,).
        frame: (4, 4) rigid local-to-parent matrix of the canonical skeleton.
    """

    code: int = -1

    def __init__(self, radius, color):
        super().__init__(())
        name = type(self).__name__
        self.radius = _check.scalar(name, "radius", radius, positive=True)
        self.color = _check.color(name, DEFAULT_COLOR if color is None else color)
        self.frame = np.eye(4)

    # kernel description -------------------------------------------------
    def params(self) -> np.ndarray:
        """Up to four kind-specific scalars for the kernel."""
        return np.zeros(4)

    def data(self) -> np.ndarray:
        """Variable-length float data for the kernel (polygon vertices, spline weights)."""
        return np.zeros(0)

    def local_skeleton_box(self):
        """``(lower, upper)`` of the skeleton in the local frame."""
        raise NotImplementedError

    def _compute_bounds(self):
        lo, hi = self.local_skeleton_box()
        grow = self.radius * (1.0 + BOX_PAD)
        return box_transform(self.frame, (np.asarray(lo) - grow, np.asarray(hi) + grow))


class Point(Primitive):
    """A point skeleton: a sphere-like blob.

    Args:
        center: (3,) position.
        radius: support radius R > 0; the lone surface is a sphere of radius 0.4541 R.
        color: RGB in [0, 1].

    Example:
        >>> import warpblob as wb
        >>> float(wb.field(wb.Point((0, 0, 0), 1.0), [[0.0, 0.0, 0.0]])[0])
        1.0
    """

    kind = "point"
    code = _kinds.POINT

    def __init__(self, center, radius, *, color=None):
        super().__init__(radius, color)
        self.center = _check.vector("Point", "center", center)
        self.frame[:3, 3] = self.center

    def local_skeleton_box(self):
        return np.zeros(3), np.zeros(3)


class Segment(Primitive):
    """A line-segment skeleton from ``a`` to ``b`` (a capsule-like blob)."""

    kind = "segment"
    code = _kinds.SEGMENT

    def __init__(self, a, b, radius, *, color=None):
        super().__init__(radius, color)
        self.a = _check.vector("Segment", "a", a)
        self.b = _check.vector("Segment", "b", b)
        axis = self.b - self.a
        self.length = float(np.linalg.norm(axis))
        if self.length < 1e-9:
            raise ModelError(f"Segment: a and b must differ, got a={a!r}, b={b!r}")
        # local x along the segment
        self.frame = frame_matrix(self.a, axis / self.length)[:, [2, 0, 1, 3]]

    def params(self):
        return np.array([self.length, 0.0, 0.0, 0.0])

    def local_skeleton_box(self):
        return np.zeros(3), np.array([self.length, 0.0, 0.0])


class _Circular(Primitive):
    def __init__(self, center, normal, size_name, size, radius, color, *, allow_zero=False):
        super().__init__(radius, color)
        name = type(self).__name__
        self.center = _check.vector(name, "center", center)
        self.normal = _check.direction(name, "normal", normal)
        self.size = _check.scalar(name, size_name, size, positive=True)
        self.frame = frame_matrix(self.center, self.normal)

    def params(self):
        return np.array([self.size, 0.0, 0.0, 0.0])

    def local_skeleton_box(self):
        return np.array([-self.size, -self.size, 0.0]), np.array([self.size, self.size, 0.0])


class Disc(_Circular):
    """A filled disc of radius ``disc_radius`` centred at ``center`` facing ``normal``."""

    kind = "disc"
    code = _kinds.DISC

    def __init__(self, center, normal, disc_radius, radius, *, color=None):
        super().__init__(center, normal, "disc_radius", disc_radius, radius, color)

    @property
    def disc_radius(self) -> float:
        return self.size


class Ring(_Circular):
    """A circle (torus-like blob) of radius ``ring_radius`` about ``normal``."""

    kind = "ring"
    code = _kinds.RING

    def __init__(self, center, normal, ring_radius, radius, *, color=None):
        super().__init__(center, normal, "ring_radius", ring_radius, radius, color)

    @property
    def ring_radius(self) -> float:
        return self.size


class Cone(Primitive):
    """A solid truncated cone from ``a`` (radius ``radius_a``) to ``b`` (``radius_b``)."""

    kind = "cone"
    code = _kinds.CONE

    def __init__(self, a, b, radius_a, radius_b, radius, *, color=None):
        super().__init__(radius, color)
        name = type(self).__name__
        self.a = _check.vector(name, "a", a)
        self.b = _check.vector(name, "b", b)
        self.radius_a = _check.scalar(name, "radius_a", radius_a, nonnegative=True)
        self.radius_b = _check.scalar(name, "radius_b", radius_b, nonnegative=True)
        if self.radius_a == 0.0 and self.radius_b == 0.0:
            raise ModelError(f"{name}: radius_a and radius_b cannot both be 0 (use Segment)")
        axis = self.b - self.a
        self.length = float(np.linalg.norm(axis))
        if self.length < 1e-9:
            raise ModelError(f"{name}: a and b must differ, got a={a!r}, b={b!r}")
        self.frame = frame_matrix(self.a, axis / self.length)

    def params(self):
        return np.array([self.length, self.radius_a, self.radius_b, 0.0])

    def local_skeleton_box(self):
        r = max(self.radius_a, self.radius_b)
        return np.array([-r, -r, 0.0]), np.array([r, r, self.length])


class Cylinder(Cone):
    """A solid cylinder of radius ``cylinder_radius`` from ``a`` to ``b``."""

    kind = "cylinder"

    def __init__(self, a, b, cylinder_radius, radius, *, color=None):
        r = _check.scalar("Cylinder", "cylinder_radius", cylinder_radius, positive=True)
        super().__init__(a, b, r, r, radius, color=color)

    @property
    def cylinder_radius(self) -> float:
        return self.radius_a


class Polygon(Primitive):
    """A filled planar polygon (convex or not) with 3-D vertices ``points`` (n >= 3).

    The vertices must lie in one plane (within 1e-6 of the polygon's size) and
    the polygon must have non-zero area.
    """

    kind = "polygon"
    code = _kinds.POLYGON

    def __init__(self, points, radius, *, color=None):
        super().__init__(radius, color)
        name = type(self).__name__
        pts = _check.points(name, "points", points, 3, 3)
        self.points = pts
        center = pts.mean(axis=0)
        # Newell normal: robust for non-convex polygons
        nxt = np.roll(pts, -1, axis=0)
        normal = np.array(
            [
                np.sum((pts[:, 1] - nxt[:, 1]) * (pts[:, 2] + nxt[:, 2])),
                np.sum((pts[:, 2] - nxt[:, 2]) * (pts[:, 0] + nxt[:, 0])),
                np.sum((pts[:, 0] - nxt[:, 0]) * (pts[:, 1] + nxt[:, 1])),
            ]
        )
        size = float(np.max(np.linalg.norm(pts - center, axis=1)))
        area2 = float(np.linalg.norm(normal))
        if size < 1e-9 or area2 < 1e-9 * size * size:
            raise ModelError(f"{name}: points span no area (degenerate polygon), got {pts.tolist()!r}")
        normal /= area2
        off_plane = np.abs((pts - center) @ normal)
        if np.max(off_plane) > 1e-6 * max(size, 1.0):
            raise ModelError(
                f"{name}: points must be coplanar, vertex {int(np.argmax(off_plane))} is "
                f"{float(np.max(off_plane)):.3g} off the plane"
            )
        self.frame = frame_matrix(center, normal)
        local = (pts - center) @ self.frame[:3, :3]
        self._local2d = local[:, :2]

    def params(self):
        return np.array([float(len(self._local2d)), 0.0, 0.0, 0.0])

    def data(self):
        return self._local2d.reshape(-1)

    def local_skeleton_box(self):
        lo = self._local2d.min(axis=0)
        hi = self._local2d.max(axis=0)
        return np.array([lo[0], lo[1], 0.0]), np.array([hi[0], hi[1], 0.0])


class Triangle(Polygon):
    """A filled triangle ``p0, p1, p2``."""

    kind = "triangle"

    def __init__(self, p0, p1, p2, radius, *, color=None):
        pts = [_check.vector("Triangle", n, v) for n, v in (("p0", p0), ("p1", p1), ("p2", p2))]
        super().__init__(np.array(pts), radius, color=color)


class Box(Primitive):
    """A solid axis-aligned box skeleton (rotate it with ``.rotate``)."""

    kind = "box"
    code = _kinds.BOX

    def __init__(self, center, half_extents, radius, *, color=None):
        super().__init__(radius, color)
        self.center = _check.vector("Box", "center", center)
        self.half_extents = _check.vector("Box", "half_extents", half_extents)
        if np.any(self.half_extents < 0.0):
            raise ModelError(f"Box: half_extents must be non-negative, got {half_extents!r}")
        self.frame[:3, 3] = self.center

    def params(self):
        return np.array([*self.half_extents, 0.0])

    def local_skeleton_box(self):
        return -self.half_extents, self.half_extents.copy()
