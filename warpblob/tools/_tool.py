"""Rigid tools: small closed triangle meshes that a :class:`~warpblob.tools.Path` moves through a model.

Every built-in tool follows one frame convention: its working end sits at
the local origin and faces local -z, and its body extends along +z. So a
tool on a path made with ``align=True`` (local -z along the travel) leads
with its working end: the probe pushes with its contact face, the scalpel
with its cutting edge, the drill with its bit. Sizes are in model units.
"""

from __future__ import annotations

import numpy as np

from .._errors import ToolError
from ._check import frozen, rows, scalar, shown
from ._pose import Pose

__all__ = ["Tool", "Probe", "Scalpel", "Drill"]


def _mesh_problem(vertices: np.ndarray, faces: np.ndarray) -> str | None:
    """Why ``faces`` over ``vertices`` is not a closed, consistently oriented mesh with every vertex used, or None."""
    f = faces.astype(np.int64)
    repeats = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    if repeats.any():
        i = int(np.argmax(repeats))
        return f"face {i} {tuple(f[i].tolist())} repeats a vertex"
    used = np.zeros(len(vertices), dtype=bool)
    used[f.ravel()] = True
    if not used.all():
        return f"vertex {int(np.argmin(used))} is used by no face"
    # directed edge c runs from corner c = 3 i + k of face i to the next corner of that face
    at, to = f.ravel(), np.roll(f, -1, axis=1).ravel()
    n = len(vertices)
    keys, counts = np.unique(at * n + to, return_counts=True)
    own = counts[np.searchsorted(keys, at * n + to)]
    slot = np.minimum(np.searchsorted(keys, to * n + at), len(keys) - 1)
    back = np.where(keys[slot] == to * n + at, counts[slot], 0)
    bad = (own != 1) | (back != 1)
    if bad.any():
        c = int(np.argmax(bad))
        a, b = int(at[c]), int(to[c])
        return (
            f"edge ({a}, {b}) of face {c // 3} runs {int(own[c])} time(s) from {a} to {b} and {int(back[c])} "
            f"from {b} to {a}; a closed, consistently oriented mesh runs every edge once each way"
        )
    return None


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume by the divergence theorem: positive when the faces wind counter-clockwise seen from outside."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def _posed(points: np.ndarray, pose) -> np.ndarray:
    """Local ``points`` in the world of ``pose`` (None: left local)."""
    if pose is None:
        return points.copy()
    if not isinstance(pose, Pose):
        raise ToolError(f"pose must be a warpblob.tools.Pose (for instance path.pose(t)), got {shown(pose)}")
    return pose.apply(points)


def _band(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Triangles of the closed band of quads ``(a[k], a[k+1], b[k+1], b[k])`` between index rings ``a`` and ``b``.

    Each quad faces the side from which ``a`` runs left to right below ``b``.
    """
    a1, b1 = np.roll(a, -1), np.roll(b, -1)
    return np.concatenate([np.stack([a, a1, b1], axis=1), np.stack([a, b1, b], axis=1)])


def _prism(outline, height: float) -> tuple[np.ndarray, np.ndarray]:
    """A convex polygon ``outline`` (K, 2), counter-clockwise in the xy plane, extruded from z = 0 to ``height``.

    Returns:
        vertices (2K, 3) (the bottom ring, then the top ring) and outward
        faces (4K - 4, 3): the side walls, then the fan-triangulated caps.
    """
    outline = np.asarray(outline, dtype=np.float64)
    k = len(outline)
    vertices = np.concatenate([np.column_stack([outline, np.zeros(k)]), np.column_stack([outline, np.full(k, height)])])
    bottom, top = np.arange(k), np.arange(k, 2 * k)
    fan = np.arange(1, k - 1)
    bottom_cap = np.column_stack([np.zeros_like(fan), fan + 1, fan])
    top_cap = np.column_stack([np.full_like(fan, k), fan + k, fan + k + 1])
    return vertices, np.concatenate([_band(bottom, top), bottom_cap, top_cap])


class Tool:
    """A rigid tool: a closed triangle mesh in its own (local) frame, placed in the world by a :class:`Pose`.

    The mesh is checked once here: finite vertices, integer faces in range,
    every vertex used, every edge run exactly once in each direction
    (closed and consistently oriented), and a positive enclosed volume
    (faces counter-clockwise seen from outside). The inputs are copied.

    Args:
        vertices: (V, 3) local positions, model units.
        faces: (F, 3) integer vertex indices.

    Attributes:
        vertices: (V, 3) float64, read-only.
        faces: (F, 3) int32, read-only.

    Raises:
        ToolError: a bad shape or value, or an open, inconsistently oriented
            or inside-out mesh; the message names the first bad vertex, face
            or edge.

    Example:
        >>> from warpblob.tools import Tool
        >>> v = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)]
        >>> Tool(v, [(0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)])
        Tool: 4 vertices, 4 triangles, volume 0.166667
        >>> try:
        ...     Tool(v, [(0, 1, 2), (0, 1, 3), (1, 2, 3), (0, 3, 2)])
        ... except ValueError as err:  # a ToolError
        ...     print(str(err)[:60])
        Tool: edge (0, 1) of face 0 runs 2 time(s) from 0 to 1 and 0
    """

    def __init__(self, vertices, faces):
        v = rows("Tool", "vertices", vertices, 3)
        f = np.array(faces)
        if f.dtype == bool or not np.issubdtype(f.dtype, np.integer):
            raise ToolError(f"Tool: faces must be integer vertex indices, got {shown(faces)}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) < 4:
            raise ToolError(f"Tool: faces must have shape (F, 3) with F >= 4 (a closed mesh), got shape {f.shape}")
        out = (f < 0) | (f >= len(v))
        if out.any():
            i = int(np.argmax(out.any(axis=1)))
            raise ToolError(f"Tool: faces[{i}] = {f[i].tolist()} indexes outside the {len(v)} vertices")
        problem = _mesh_problem(v, f)
        if problem:
            raise ToolError(f"Tool: {problem}")
        volume = _signed_volume(v, f)
        if not volume > 0:
            raise ToolError(
                f"Tool: the mesh encloses volume {volume:.6g}: it must be positive (faces counter-clockwise "
                "seen from outside; reverse each face of an inside-out mesh)"
            )
        self.vertices = frozen(v)
        self.faces = frozen(f.astype(np.int32))
        self._samples: dict = {}

    @property
    def vertex_count(self) -> int:
        return len(self.vertices)

    @property
    def face_count(self) -> int:
        return len(self.faces)

    def is_closed(self) -> bool:
        """Whether the mesh is closed and consistently oriented (always, once constructed: it is checked then)."""
        return _mesh_problem(self.vertices, self.faces) is None

    def volume(self) -> float:
        """Enclosed volume, model units cubed (divergence theorem)."""
        return _signed_volume(self.vertices, self.faces)

    def world_vertices(self, pose=None) -> np.ndarray:
        """The vertices placed by ``pose``: (V, 3), or (N, V, 3) for a batch of N poses; local for None."""
        return _posed(self.vertices, pose)

    def bounds(self, pose=None) -> np.ndarray:
        """Axis-aligned box ``[lower, upper]`` of the posed vertices: (2, 3), or (N, 2, 3) for a batch."""
        w = self.world_vertices(pose)
        return np.stack([w.min(axis=-2), w.max(axis=-2)], axis=-2)

    def sample_surface(self, spacing: float, *, pose=None) -> np.ndarray:
        """Points on the tool's faces about ``spacing`` apart, for contact tests against a model's field.

        The points are, in this order: every vertex; on every edge of length
        ``l``, the ``ceil(l / spacing) - 1`` points that divide it evenly;
        inside every triangle whose longest edge is ``l``, the interior nodes
        of its barycentric grid with ``n = ceil(l / spacing)`` divisions
        (weights ``(i, j, n - i - j) / n``, all three >= 1/n). No point is
        repeated, and neighbours are at most about ``spacing`` apart (closer
        along short edges). The local points are cached for the last spacing.

        Args:
            spacing: model units, > 0; contact uses the model mesh's edge length.
            pose: place the points in the world (a single pose or a batch); None: local.

        Returns:
            (S, 3) float64, or (N, S, 3) for a batch of N poses.

        Raises:
            ToolError: ``spacing`` is not a positive number.

        Example:
            >>> from warpblob.tools import Probe
            >>> len(Probe(1.0).sample_surface(1.0))  # 8 corners, the midpoints of the 6 face diagonals
            14
        """
        spacing = scalar("Tool.sample_surface", "spacing", spacing, positive=True)
        local = self._samples.get(spacing)
        if local is None:
            local = frozen(self._sample(spacing))
            self._samples = {spacing: local}
        return _posed(local, pose)

    def _sample(self, spacing: float) -> np.ndarray:
        v, f = self.vertices, self.faces.astype(np.int64)
        edges = np.unique(np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
        a, b = v[edges[:, 0]], v[edges[:, 1]]
        divisions = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / spacing), 1).astype(np.int64)
        inner = divisions - 1
        edge = np.repeat(np.arange(len(edges)), inner)
        first = np.repeat(np.cumsum(inner) - inner, inner)
        t = (np.arange(inner.sum()) - first + 1) / divisions[edge]
        on_edges = a[edge] + t[:, None] * (b[edge] - a[edge])
        corners = v[f]
        longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
        grid = np.ceil(longest / spacing).astype(np.int64)
        inside = []
        # one pass per distinct grid size (a handful for a tool), each over all its triangles at once
        for n in np.unique(grid[grid >= 3]):
            i, j = np.meshgrid(np.arange(1, n), np.arange(1, n), indexing="ij")
            keep = i + j <= n - 1
            weights = np.column_stack([i[keep], j[keep], n - i[keep] - j[keep]]) / n
            inside.append(np.einsum("kc,fcd->fkd", weights, corners[grid == n]).reshape(-1, 3))
        return np.concatenate([v, on_edges] + inside)

    def to_pyvista(self, pose=None):
        """A ``pyvista.PolyData`` of the mesh placed by a single ``pose`` (None: local)."""
        import pyvista as pv

        if pose is not None and isinstance(pose, Pose) and pose.shape:
            raise ToolError(f"Tool.to_pyvista: pose must be a single pose, got a batch of {pose.shape[0]}")
        faces = np.column_stack([np.full(self.face_count, 3, dtype=np.int64), self.faces]).ravel()
        return pv.PolyData(self.world_vertices(pose), faces)

    def _describe(self) -> str:
        return type(self).__name__

    def __repr__(self) -> str:
        counts = f"{self.vertex_count} vertices, {self.face_count} triangles"
        return f"{self._describe()}: {counts}, volume {self.volume():.6g}"


class Probe(Tool):
    """A cube probe for pushing tissue: side ``size``, contact face on the local xy plane.

    The cube spans ``[-size/2, size/2]`` in x and y and ``[0, size]`` in z:
    the local origin is the centre of its bottom (contact) face, so a path
    gives the contact face's position. Pushing straight down needs no
    rotation (``Path.line(..., align=True)`` gives the identity).

    Args:
        size: edge length, model units, > 0.

    Example:
        >>> from warpblob.tools import Probe
        >>> Probe(2.0)
        Probe(size=2): 8 vertices, 12 triangles, volume 8
        >>> Probe(2.0).bounds()
        array([[-1., -1.,  0.],
               [ 1.,  1.,  2.]])
    """

    def __init__(self, size: float):
        self.size = scalar("Probe", "size", size, positive=True)
        h = 0.5 * self.size
        super().__init__(*_prism([(-h, -h), (h, -h), (h, h), (-h, h)], self.size))

    def _describe(self) -> str:
        return f"Probe(size={self.size:g})"


class Scalpel(Tool):
    """A scalpel blade: a thin wedge whose sharp edge is the cutting edge.

    The cutting edge runs along local +y from the tip ``(0, 0, 0)`` to the
    heel ``(0, length, 0)``; the blade extends ``width`` behind it along +z
    and thickens evenly in x to ``thickness`` at its back. So the tip is the
    local origin (a path gives the tip's position), the edge leads along -z,
    and on a horizontal path with ``align=True`` the edge stands vertical,
    tip down (local +y goes to world up). The mesh is a triangular prism
    (6 vertices): the edge's end points are vertices and the edge a mesh
    edge.

    Args:
        length: cutting edge length, model units, > 0.
        width: blade depth behind the edge, model units, > 0.
        thickness: back thickness, model units, > 0; default ``width / 10``.

    Attributes:
        edge: (2, 3) float64 local ``[tip, heel]``.

    Example:
        >>> from warpblob.tools import Path, Scalpel
        >>> blade = Scalpel(2.0, 0.5)
        >>> tip, heel = blade.edge_points(Path.line((0, 0, 0), (1, 0, 0), 1.0, align=True).pose(0.5))
        >>> tip.round(6) + 0.0, heel.round(6) + 0.0
        (array([0.5, 0. , 0. ]), array([0.5, 0. , 2. ]))
    """

    def __init__(self, length: float, width: float, *, thickness: float | None = None):
        self.length = scalar("Scalpel", "length", length, positive=True)
        self.width = scalar("Scalpel", "width", width, positive=True)
        self.thickness = (0.1 * self.width if thickness is None
                          else scalar("Scalpel", "thickness", thickness, positive=True))  # fmt: skip
        half = 0.5 * self.thickness
        # the cross-section in the (z, x) plane, extruded along y: cycling the prism's axes (x, y, z) -> (z, x, y)
        # is a rotation, so the faces stay outward
        vertices, faces = _prism([(0.0, 0.0), (self.width, -half), (self.width, half)], self.length)
        super().__init__(vertices[:, [1, 2, 0]], faces)
        self.edge = frozen(self.vertices[[0, 3]].copy())

    def edge_points(self, pose=None) -> tuple[np.ndarray, np.ndarray]:
        """World ``(tip, heel)`` of the cutting edge: each (3,), or (N, 3) for a batch of N poses; local for None."""
        tip, heel = _posed(self.edge, pose).swapaxes(0, -2)
        return tip, heel

    def _describe(self) -> str:
        return f"Scalpel(length={self.length:g}, width={self.width:g}, thickness={self.thickness:g})"


class Drill(Tool):
    """A trephine: a tube about local z from the bit (z = 0) to z = ``length``.

    The cutting surface is the cylinder of ``radius`` about z, approximated
    by ``segments`` flat side-wall quads (:meth:`wall_quads`) whose corners
    lie on it. The mesh is that tube given a wall: a closed tube whose inner
    and outer faces are the same polygon at ``radius - thickness / 2`` and
    ``radius + thickness / 2``, joined by flat annuli at both ends (the bit's
    cutting ring at z = 0). Being hollow, it has no vertex or face over the
    plug it cuts out, so contact does not push the plug.

    Args:
        radius: cut radius (the wall's middle), model units, > 0.
        length: model units, > 0.
        segments: number of side-wall quads, >= 3.
        thickness: wall thickness, model units, in (0, 2 radius); default ``radius / 10``.

    Example:
        >>> from warpblob.tools import Drill
        >>> drill = Drill(0.5, 2.0, segments=8)
        >>> drill.wall_quads().shape, drill.face_count
        ((8, 4, 3), 64)
    """

    def __init__(self, radius: float, length: float, *, segments: int = 16, thickness: float | None = None):
        self.radius = scalar("Drill", "radius", radius, positive=True)
        self.length = scalar("Drill", "length", length, positive=True)
        if isinstance(segments, bool) or not isinstance(segments, (int, np.integer)) or segments < 3:
            raise ToolError(f"Drill: segments must be an integer >= 3, got {shown(segments)}")
        self.segments = int(segments)
        self.thickness = (0.1 * self.radius if thickness is None
                          else scalar("Drill", "thickness", thickness, positive=True))  # fmt: skip
        if not self.thickness < 2 * self.radius:
            raise ToolError(f"Drill: thickness must be less than 2 * radius = {2 * self.radius:g}, got {thickness!r}")
        angle = 2 * np.pi * np.arange(self.segments) / self.segments
        self._circle = np.column_stack([np.cos(angle), np.sin(angle)])
        rings = [(r, z) for r in (self.radius + 0.5 * self.thickness, self.radius - 0.5 * self.thickness)
                 for z in (0.0, self.length)]  # fmt: skip
        vertices = np.concatenate([np.column_stack([r * self._circle, np.full(self.segments, z)]) for r, z in rings])
        outer_bit, outer_top, inner_bit, inner_top = np.arange(4 * self.segments).reshape(4, self.segments)
        faces = np.concatenate([_band(outer_bit, outer_top), _band(inner_top, inner_bit),
                                _band(inner_bit, outer_bit), _band(outer_top, inner_top)])  # fmt: skip
        super().__init__(vertices, faces)

    def wall_quads(self, pose=None) -> np.ndarray:
        """The side wall as quads on the cylinder of ``radius``: (segments, 4, 3), or (N, segments, 4, 3) for a batch.

        Quad ``k`` spans the angles ``2 pi k / segments`` to ``2 pi (k + 1) /
        segments``; its corners run bit, bit, top, top (counter-clockwise seen
        from outside, so its normal points away from the axis).
        """
        ring = np.column_stack([self.radius * self._circle, np.zeros(self.segments)])
        bit, bit_next = ring, np.roll(ring, -1, axis=0)
        top, top_next = bit + (0.0, 0.0, self.length), bit_next + (0.0, 0.0, self.length)
        return _posed(np.stack([bit, bit_next, top_next, top], axis=1), pose)

    def _describe(self) -> str:
        return (
            f"Drill(radius={self.radius:g}, length={self.length:g}, segments={self.segments}, "
            f"thickness={self.thickness:g})"
        )
