"""The surface a blade sweeps (SPEC section 6.1): triangles that the mesh edges are cut against.

A scalpel's cutting edge, sampled along its path, traces a strip of quads
(consecutive samples of the edge's two end points), each split into two
triangles, as in the thesis (Shirazian 2014, VolCut, section 6.1). A drill's
side wall traces one strip per wall segment. Recording starts when the
tool's box meets the model's box grown by a margin and stops when it leaves
it, so a stroke that starts far away costs nothing.
"""

from __future__ import annotations

import numpy as np

from .._errors import CutError

__all__ = ["SweepSurface", "cutting_edges"]

#: a triangle whose area is below this fraction of its longest edge squared is dropped (the blade stood still)
_SLIVER = 1e-12


def _points(name: str, value) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CutError(f"SweepSurface: {name} must be numbers, got {value!r}") from exc
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise CutError(f"SweepSurface: {name} must have shape (T, 3), got {arr.shape}")
    bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
    if bad.size:
        raise CutError(f"SweepSurface: {name}[{bad[0]}] = {arr[bad[0]].tolist()} is not finite")
    return arr


class SweepSurface:
    """Triangles swept by a blade, in the world frame of the mesh's current positions.

    Build one with :meth:`from_blade`, :meth:`from_path` or :meth:`plane`.

    Attributes:
        triangles: (M, 3, 3) float64 triangle corners, model units.
        strips: (M,) int32 the strip each triangle belongs to (one per blade,
            one per drill wall segment). Triangles are in the order they are
            swept (a drill's: sample by sample, every segment of a sample
            together): a mesh edge keeps its first hit.

    Example:
        >>> import numpy as np
        >>> s = SweepSurface.from_blade([[0, 0, 0], [1, 0, 0]], [[0, 0, 1], [1, 0, 1]])
        >>> s.triangles.shape, s.area()
        ((2, 3, 3), 1.0)
    """

    def __init__(self, triangles, strips=None):
        tri = np.array(triangles, dtype=np.float64)
        if tri.ndim != 3 or tri.shape[1:] != (3, 3):
            raise CutError(f"SweepSurface: triangles must have shape (M, 3, 3), got {tri.shape}")
        if not np.isfinite(tri).all():
            bad = int(np.flatnonzero(~np.isfinite(tri).all(axis=(1, 2)))[0])
            raise CutError(f"SweepSurface: triangle {bad} has corners {tri[bad].tolist()}, not all finite")
        strips = np.zeros(len(tri), dtype=np.int32) if strips is None else np.asarray(strips, dtype=np.int32)
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        longest = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
        keep = np.linalg.norm(cross, axis=1) > _SLIVER * np.maximum(longest, 1e-300) ** 2
        self.triangles = tri[keep]
        self.strips = strips[keep]
        self.triangles.flags.writeable = False
        self.strips.flags.writeable = False

    @property
    def triangle_count(self) -> int:
        """Triangles (degenerate ones dropped)."""
        return len(self.triangles)

    def area(self) -> float:
        """Total area, model units squared."""
        t = self.triangles
        return float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())

    def normals(self) -> np.ndarray:
        """(M, 3) unit normals (right-handed in corner order)."""
        t = self.triangles
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned box ``[lower, upper]`` of the triangles."""
        if not len(self.triangles):
            return np.zeros((2, 3))
        p = self.triangles.reshape(-1, 3)
        return np.stack([p.min(axis=0), p.max(axis=0)])

    def __repr__(self) -> str:
        return f"SweepSurface({self.triangle_count} triangles, area {self.area():.4g})"

    # -- constructors -----------------------------------------------------------------

    @classmethod
    def from_blade(cls, a_points, b_points) -> SweepSurface:
        """The strip traced by a blade's two end points sampled along its stroke.

        Args:
            a_points: (T, 3) one end of the cutting edge at each sample (T >= 2).
            b_points: (T, 3) the other end at the same samples.

        Returns:
            ``2 (T - 1)`` triangles, quad ``i`` = ``a_i, b_i, b_{i+1}, a_{i+1}``.

        Raises:
            CutError: a shape is wrong, a point is not finite, or T < 2.
        """
        a, b = _points("a_points", a_points), _points("b_points", b_points)
        if len(a) != len(b):
            raise CutError(f"SweepSurface.from_blade: {len(a)} a_points but {len(b)} b_points")
        if len(a) < 2:
            raise CutError(f"SweepSurface.from_blade: a stroke needs at least two samples, got {len(a)}")
        return cls.from_edges(a[:, None], b[:, None])

    @classmethod
    def plane(cls, origin, normal, extent: float) -> SweepSurface:
        """A square of half-width ``extent`` centred at ``origin`` across ``normal``: a cut straight through.

        Args:
            origin: (3,) a point of the plane.
            normal: (3,) its normal (any length > 0); the square's normals point along it.
            extent: half the square's side, model units, > 0 (make it larger than the model).

        Example:
            >>> SweepSurface.plane((0, 0, 0), (0, 0, 1), 2.0).area()
            16.0
        """
        o = _points("origin", [origin])[0]
        n = _points("normal", [normal])[0]
        length = float(np.linalg.norm(n))
        if length == 0.0:
            raise CutError(f"SweepSurface.plane: normal must not be zero, got {list(normal)!r}")
        if not (isinstance(extent, (int, float, np.floating)) and np.isfinite(extent) and extent > 0):
            raise CutError(f"SweepSurface.plane: extent must be a positive number, got {extent!r}")
        n = n / length
        u = np.cross(n, (1.0, 0.0, 0.0) if abs(n[0]) < 0.9 else (0.0, 1.0, 0.0))
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        e = float(extent)
        a = np.stack([o - e * u - e * v, o - e * u + e * v])
        b = np.stack([o + e * u - e * v, o + e * u + e * v])
        # quad a0, b0, b1, a1 has normal (u x v) = n
        return cls(_strip(a, b))

    @classmethod
    def from_path(cls, tool, path, t0: float | None = None, t1: float | None = None, dt: float = 1.0 / 60.0, *,
                  bounds=None, margin: float = 0.05) -> SweepSurface:  # fmt: skip
        """The surface a tool's cutting part sweeps along ``path`` from ``t0`` to ``t1``, sampled every ``dt``.

        A :class:`~warpblob.tools.Scalpel` sweeps its cutting edge (one
        strip); a :class:`~warpblob.tools.Drill` sweeps its side wall (one
        strip per wall segment: the bit ring's trajectory, plus the wall at
        the first recorded pose, so a drill that starts inside the material
        cuts along its whole tube).

        Args:
            tool: a Scalpel or Drill.
            path: a :class:`~warpblob.tools.Path`.
            t0, t1: seconds (default: the path's start and end).
            dt: sampling step, seconds, > 0 (the end time is always a sample).
            bounds: optional (2, 3) model box; samples are kept only while the
                tool's box meets it grown by ``margin`` times its diagonal
                (SPEC 6.1); None keeps every sample.
            margin: the growth, as a fraction of the box diagonal.

        Raises:
            CutError: a tool that does not cut, a bad time range, or fewer
                than two samples left.
        """
        from ..tools import Drill, Scalpel

        if not isinstance(tool, (Scalpel, Drill)):
            raise CutError(f"SweepSurface.from_path: tool must be a Scalpel or a Drill, got {type(tool).__name__}")
        t0 = path.t0 if t0 is None else t0
        t1 = path.t1 if t1 is None else t1
        for name, value in (("t0", t0), ("t1", t1), ("dt", dt)):
            if not (isinstance(value, (int, float, np.floating)) and np.isfinite(value)):
                raise CutError(f"SweepSurface.from_path: {name} must be a finite number, got {value!r}")
        if not dt > 0 or not t1 > t0:
            raise CutError(f"SweepSurface.from_path: need dt > 0 and t1 > t0, got t0={t0!r}, t1={t1!r}, dt={dt!r}")
        times = np.append(np.arange(float(t0), float(t1), float(dt)), float(t1))
        poses = path.pose(times)
        if bounds is not None:
            box = np.array(bounds, dtype=np.float64).reshape(2, 3)
            grow = margin * float(np.linalg.norm(box[1] - box[0]))
            tb = tool.bounds(poses)
            meets = np.all((tb[:, 0] <= box[1] + grow) & (tb[:, 1] >= box[0] - grow), axis=1)
            if not meets.any():
                return cls(np.zeros((0, 3, 3)))
            first, last = np.flatnonzero(meets)[[0, -1]]
            first, last = max(first - 1, 0), min(last + 1, len(times) - 1)
            poses = path.pose(times[first : last + 1])
        if len(np.atleast_2d(poses.position)) < 2:
            raise CutError("SweepSurface.from_path: the stroke leaves fewer than two samples")
        return cls.from_edges(*cutting_edges(tool, poses, first=True))

    @classmethod
    def from_edges(cls, a, b) -> SweepSurface:
        """The strips traced by ``S`` cutting edges sampled ``R`` times: (R, S, 3) end points ``a`` and ``b``
        (:func:`cutting_edges`); strip ``s`` joins the edges ``a[:, s] - b[:, s]`` of consecutive samples.

        Triangles are time-major (sample by sample, every strip of a sample together): an edge keeps its first hit.
        """
        a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
        if a.ndim != 3 or a.shape != b.shape or a.shape[2] != 3 or len(a) < 2:
            raise CutError(f"SweepSurface.from_edges: a and b must be (R >= 2, S, 3) alike, got {a.shape}, {b.shape}")
        strips = np.broadcast_to(np.arange(a.shape[1], dtype=np.int32)[None, :, None], (len(a) - 1, a.shape[1], 2))
        return cls(_strip(a, b), strips.reshape(-1))


def cutting_edges(tool, poses, *, first: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """The cutting edges of a Scalpel or Drill at ``poses``: (R, S, 3) end points ``a`` and ``b``.

    A scalpel has one edge (S = 1: tip and heel), R = the poses. A drill has
    one per wall segment (S = segments: the bit ring's edges); with ``first``
    its wall's top edges at the first pose come first (R = poses + 1), so the
    strips also cover the wall where the drill starts (a drill that starts
    inside the material cuts along its whole tube).
    """
    from ..tools import Scalpel

    if isinstance(tool, Scalpel):
        a, b = tool.edge_points(poses)
        return np.atleast_2d(a)[:, None], np.atleast_2d(b)[:, None]
    quads = tool.wall_quads(poses)  # (T, S, 4, 3): bit, bit_next, top_next, top
    if quads.ndim == 3:
        quads = quads[None]
    a, b = quads[:, :, 0], quads[:, :, 1]
    if first:
        a, b = np.concatenate([quads[:1, :, 3], a]), np.concatenate([quads[:1, :, 2], b])
    return a, b


def _strip(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Triangles of the quads ``a_i, b_i, b_{i+1}, a_{i+1}`` along the first axis of (T, ..., 3) ``a`` and ``b``:
    (2 (T - 1) x ..., 3, 3), the two of a quad together, quads in order."""
    first = np.stack([a[:-1], b[:-1], b[1:]], axis=-2)
    second = np.stack([a[:-1], b[1:], a[1:]], axis=-2)
    return np.stack([first, second], axis=-3).reshape(-1, 3, 3)
