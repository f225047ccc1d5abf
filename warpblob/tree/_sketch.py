"""Sketched primitives: variational implicit curves made solid.

A closed 2-D contour is turned into a smooth 2-D field by a thin-plate spline
(Turk & O'Brien 1999, "Shape transformation using variational implicit
functions"; Turk & O'Brien 2002 for the normal constraints), as in ShapeShop
(Schmidt, Wyvill, Sousa & Jorge 2005):

    s(u) = sum_i w_i |u - m_i|^2 ln|u - m_i| + c1 u_x + c2 u_y + c3

with ``s = 0`` on contour samples, ``s = +delta`` at samples offset inwards by
``delta`` and ``s = -delta`` outwards, so ``s`` approximates the signed
distance near the contour (positive inside). The weights come from one dense
linear solve with the polynomial side conditions.

The 3-D primitives measure distance to a solid skeleton through

    o(u) = max(-s(u), e(u), 0)

where ``e`` is the exact distance to the contour's bounding rectangle; ``e``
makes the support provably bounded (``o >= R`` outside the rectangle grown
by ``R``) whatever the spline does far from the contour.
"""

from __future__ import annotations

import numpy as np

from .._errors import ModelError
from . import _check, _kinds
from ._node import BOX_PAD, box_union, frame_matrix, rotation_matrix
from ._primitives import Primitive

__all__ = ["Sketch", "Inflate", "Revolve", "Sweep"]

_SAMPLES = 32


def _tps_kernel(r):
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(r > 0.0, r * r * np.log(np.where(r > 0.0, r, 1.0)), 0.0)


def _segments_intersect(p):
    """The first pair ``(i, j)`` of non-adjacent edges of the closed polygon ``p`` that cross, or None."""
    n = len(p)
    a, b = p, np.roll(p, -1, axis=0)

    def orient(u, v, w):
        return np.sign((v[..., 0] - u[..., 0]) * (w[..., 1] - u[..., 1]) - (v[..., 1] - u[..., 1]) * (w[..., 0] - u[..., 0]))

    i, j = np.triu_indices(n, k=2)
    keep = ~((i == 0) & (j == n - 1))
    i, j = i[keep], j[keep]
    o1 = orient(a[i], b[i], a[j])
    o2 = orient(a[i], b[i], b[j])
    o3 = orient(a[j], b[j], a[i])
    o4 = orient(a[j], b[j], b[i])
    hit = np.nonzero((o1 * o2 < 0) & (o3 * o4 < 0))[0]
    return (int(i[hit[0]]), int(j[hit[0]])) if len(hit) else None


class Sketch:
    """A closed 2-D contour fitted with a thin-plate spline.

    Args:
        points2d: (n, 2) vertices of a simple closed polygon, n >= 3, in
            either orientation (the closing edge is implicit).

    Attributes:
        centers: (m, 2) spline centres; weights: (m,); affine: (3,) ``c1, c2, c3``.
        lower, upper: (2,) bounding rectangle of the contour.
        depth: the largest value of the spline inside the contour (about the
            inradius), used to shape inflation.

    Example:
        >>> import warpblob as wb
        >>> s = wb.Sketch([[0, 0], [1, 0], [1, 1], [0, 1]])
        >>> bool(s.evaluate([[0.5, 0.5]])[0] > 0.0), bool(s.evaluate([[2.0, 2.0]])[0] < 0.0)
        (True, True)
    """

    def __init__(self, points2d):
        pts = _check.points("Sketch", "points2d", points2d, 2, 3)
        if np.allclose(pts[0], pts[-1]):
            pts = pts[:-1]
        if len(pts) < 3:
            raise ModelError(f"Sketch: points2d needs at least 3 distinct vertices, got {len(pts)}")
        area = 0.5 * float(np.sum(pts[:, 0] * np.roll(pts[:, 1], -1) - np.roll(pts[:, 0], -1) * pts[:, 1]))
        size = float(np.max(np.ptp(pts, axis=0)))
        if abs(area) < 1e-6 * size * size or size < 1e-9:
            raise ModelError(f"Sketch: points2d encloses no area (degenerate contour), got area {area:.3g}")
        crossing = _segments_intersect(pts)
        if crossing is not None:
            i, j = crossing
            raise ModelError(
                f"Sketch: points2d must be a simple polygon; edge {i} ({pts[i].tolist()} -> "
                f"{pts[(i + 1) % len(pts)].tolist()}) crosses edge {j} ({pts[j].tolist()} -> {pts[(j + 1) % len(pts)].tolist()})"
            )
        if area < 0.0:
            pts = pts[::-1]
        self.points = pts
        self.lower = pts.min(axis=0)
        self.upper = pts.max(axis=0)
        self._fit(pts, size)

    def _fit(self, pts, size):
        # resample the contour uniformly by arc length
        closed = np.vstack([pts, pts[:1]])
        seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg)])
        s = np.linspace(0.0, cum[-1], _SAMPLES, endpoint=False)
        samples = np.column_stack([np.interp(s, cum, closed[:, 0]), np.interp(s, cum, closed[:, 1])])
        tangent = np.roll(samples, -1, axis=0) - np.roll(samples, 1, axis=0)
        tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
        inward = np.column_stack([-tangent[:, 1], tangent[:, 0]])  # counter-clockwise contour
        delta = 0.05 * size
        centers = np.vstack([samples, samples + delta * inward, samples - delta * inward])
        values = np.concatenate([np.zeros(_SAMPLES), np.full(_SAMPLES, delta), np.full(_SAMPLES, -delta)])
        m = len(centers)
        a = _tps_kernel(np.linalg.norm(centers[:, None] - centers[None], axis=2))
        p = np.column_stack([centers, np.ones(m)])
        lhs = np.zeros((m + 3, m + 3))
        lhs[:m, :m], lhs[:m, m:], lhs[m:, :m] = a, p, p.T
        rhs = np.concatenate([values, np.zeros(3)])
        try:
            sol = np.linalg.solve(lhs, rhs)
        except np.linalg.LinAlgError:
            raise ModelError("Sketch: the thin-plate spline system is singular for this contour") from None
        self.centers = centers
        self.weights = sol[:m]
        self.affine = sol[m:]
        grid = np.stack(
            np.meshgrid(np.linspace(self.lower[0], self.upper[0], 48), np.linspace(self.lower[1], self.upper[1], 48)),
            axis=-1,
        ).reshape(-1, 2)
        self.depth = max(float(np.max(self.evaluate(grid))), delta)

    def evaluate(self, u) -> np.ndarray:
        """The spline ``s(u)`` at (n, 2) points (numpy, float64)."""
        u = np.asarray(u, dtype=np.float64).reshape(-1, 2)
        r = np.linalg.norm(u[:, None] - self.centers[None], axis=2)
        return _tps_kernel(r) @ self.weights + u @ self.affine[:2] + self.affine[2]

    def data(self) -> np.ndarray:
        """Flat kernel block: ``m, lower(2), upper(2), depth, c1, c2, c3, (x, y, w) * m``."""
        head = [len(self.centers), *self.lower, *self.upper, self.depth, *self.affine]
        body = np.column_stack([self.centers, self.weights]).reshape(-1)
        return np.concatenate([np.asarray(head, dtype=np.float64), body])


def _sketch_arg(owner, sketch):
    if not isinstance(sketch, Sketch):
        raise ModelError(f"{owner}: sketch must be a warpblob Sketch, got {sketch!r}")
    return sketch


class Inflate(Primitive):
    """The sketch inflated into a pillow in its own xy plane.

    The skeleton is ``{(u, z): s(u) >= 0, |z| <= h(u)}`` with the half
    thickness ``h(u) = thickness * w(s(u) / depth)``, ``w(t) = 1 - (1 - t)^2``
    for t in [0, 1]; distance is measured as ``sqrt(o(u)^2 + max(|z| - h, 0)^2)``.

    Args:
        sketch: the contour.
        thickness: largest half thickness of the skeleton, model units, >= 0.
        radius: support radius R > 0.
    """

    kind = "inflate"
    code = _kinds.INFLATE

    def __init__(self, sketch: Sketch, *, thickness: float = 0.1, radius: float = 0.5, color=None):
        super().__init__(radius, color)
        self.sketch = _sketch_arg("Inflate", sketch)
        self.thickness = _check.scalar("Inflate", "thickness", thickness, nonnegative=True)

    def params(self):
        return np.array([self.thickness, 0.0, 0.0, 0.0])

    def data(self):
        return self.sketch.data()

    def local_skeleton_box(self):
        lo, hi = self.sketch.lower, self.sketch.upper
        return np.array([lo[0], lo[1], -self.thickness]), np.array([hi[0], hi[1], self.thickness])


class Revolve(Primitive):
    """The sketch revolved about an axis: sketch x is the distance from the
    axis, sketch y the position along it.

    Args:
        sketch: the profile; its vertices must have x >= 0.
        axis: (3,) axis direction (default +z).
        center: (3,) a point on the axis (default the origin).
        radius: support radius R > 0.
    """

    kind = "revolve"
    code = _kinds.REVOLVE

    def __init__(self, sketch: Sketch, axis=(0.0, 0.0, 1.0), center=(0.0, 0.0, 0.0), *, radius: float = 0.5, color=None):
        super().__init__(radius, color)
        self.sketch = _sketch_arg("Revolve", sketch)
        if self.sketch.lower[0] < 0.0:
            raise ModelError(
                f"Revolve: the profile must lie at x >= 0 (distance from the axis), got x down to {self.sketch.lower[0]:.3g}"
            )
        self.axis = _check.direction("Revolve", "axis", axis)
        self.center = _check.vector("Revolve", "center", center)
        self.frame = frame_matrix(self.center, self.axis)

    def data(self):
        return self.sketch.data()

    def local_skeleton_box(self):
        lo, hi = self.sketch.lower, self.sketch.upper
        return np.array([-hi[0], -hi[0], lo[1]]), np.array([hi[0], hi[0], hi[1]])


class Sweep(Primitive):
    """The sketch swept along a polyline ``path``.

    The cross-section is carried by parallel-transported frames (sketch x along
    the frame normal, y along the binormal); the distance is the smallest over
    the path's segments of ``sqrt(o(u)^2 + a^2)``, with ``a`` the distance past
    the segment's ends along its tangent. A straight path gives an extrusion.

    Args:
        sketch: the cross-section.
        path: (k, 3) polyline, k >= 2, consecutive points distinct.
        radius: support radius R > 0.
    """

    kind = "sweep"
    code = _kinds.SWEEP

    def __init__(self, sketch: Sketch, path, *, radius: float = 0.5, color=None):
        super().__init__(radius, color)
        self.sketch = _sketch_arg("Sweep", sketch)
        self.path = _check.points("Sweep", "path", path, 3, 2)
        steps = np.diff(self.path, axis=0)
        lengths = np.linalg.norm(steps, axis=1)
        if np.any(lengths < 1e-9):
            raise ModelError(f"Sweep: consecutive path points must differ (segment {int(np.argmin(lengths))} has zero length)")
        tangents = steps / lengths[:, None]
        frames = [frame_matrix(self.path[0], tangents[0])[:3, :3]]
        for k in range(1, len(tangents)):
            # parallel transport: turn the previous frame by the rotation taking
            # the previous tangent to this one (Bishop frames)
            t0, t1 = tangents[k - 1], tangents[k]
            axis = np.cross(t0, t1)
            sin, cos = float(np.linalg.norm(axis)), float(np.dot(t0, t1))
            if sin < 1e-9 and cos < 0.0:
                raise ModelError(f"Sweep: the path turns back on itself at point {k} ({self.path[k].tolist()})")
            turn = rotation_matrix(axis / sin, np.arctan2(sin, cos)) if sin >= 1e-9 else np.eye(3)
            normal = turn @ frames[-1][:, 0]
            frames.append(frame_matrix(np.zeros(3), t1, normal)[:3, :3])
        self._rotations = np.array(frames)  # columns: normal, binormal, tangent
        self._lengths = lengths

    def data(self):
        segments = []
        for origin, rot, length in zip(self.path[:-1], self._rotations, self._lengths):
            inv = rot.T  # parent -> segment local
            segments.append(np.concatenate([np.column_stack([inv, -inv @ origin]).reshape(-1), [length]]))
        return np.concatenate([self.sketch.data(), [len(segments)], np.concatenate(segments)])

    def local_skeleton_box(self):
        raise NotImplementedError  # Sweep overrides _compute_bounds

    def _compute_bounds(self):
        lo, hi = self.sketch.lower, self.sketch.upper
        grow = self.radius * (1.0 + BOX_PAD)
        boxes = []
        for origin, rot, length in zip(self.path[:-1], self._rotations, self._lengths):
            corners = np.array(
                [[x, y, z] for x in (lo[0] - grow, hi[0] + grow) for y in (lo[1] - grow, hi[1] + grow) for z in (-grow, length + grow)]
            )
            world = corners @ rot.T + origin
            boxes.append((world.min(axis=0), world.max(axis=0)))
        return box_union(boxes)
