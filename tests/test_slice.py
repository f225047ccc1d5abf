"""Planar slicing and capping (warpblob.slice) against analytic and independent references.

The references are computed here without the slicer: each triangle is
clipped against the half-space in float64 (Sutherland-Hodgman on one
triangle), which gives the exact volume of the part below (divergence
theorem with the apex on the plane, where the cap adds nothing) and its
section area (the side's area vectors sum to minus the cap's). Analytic
areas come from the polygons the test meshes are built from.
"""

from __future__ import annotations

import numpy as np
import pytest

import warpblob as wb
from warpblob.mesh import SurfaceMesh
from warpblob.slice import CAP_COLOR
from warpblob.slice import slice as slice_mesh
from warpblob.slice import _kernels

# ---------------------------------------------------------------------------
# closed test meshes, counter-clockwise seen from outside
# ---------------------------------------------------------------------------


def _mesh(vertices, faces, colors=None) -> SurfaceMesh:
    v = np.asarray(vertices, dtype=np.float32)
    c = np.full_like(v, 0.7) if colors is None else np.asarray(colors, dtype=np.float32)
    return SurfaceMesh(v, np.asarray(faces, dtype=np.int32), np.zeros_like(v), c)


def _merged(points, faces):
    """Merge points at the same (integer or exact) position into one vertex."""
    unique, inverse = np.unique(np.asarray(points), axis=0, return_inverse=True)
    return unique, inverse.reshape(-1)[np.asarray(faces)]


def grid_box(nx: int, ny: int, nz: int, h: float = 1.0) -> SurfaceMesh:
    """The surface of the box [0, nx h] x [0, ny h] x [0, nz h], a grid of h-squares, two triangles each."""
    n = (nx, ny, nz)
    points, faces = [], []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3  # (b, c, a) right-handed
        for side in (0, n[a]):
            i, j = np.meshgrid(np.arange(n[b]), np.arange(n[c]), indexing="ij")
            corners = np.stack([(i, j), (i + 1, j), (i + 1, j + 1), (i, j + 1)], axis=-1).reshape(2, -1, 4)
            quad = np.zeros((corners.shape[1], 4, 3), dtype=np.int64)
            quad[:, :, a] = side
            quad[:, :, b] = corners[0]
            quad[:, :, c] = corners[1]
            if side == 0:
                quad = quad[:, ::-1]
            base = sum(len(p) for p in points)
            points.append(quad.reshape(-1, 3))
            k = base + 4 * np.arange(len(quad))[:, None]
            faces.append(np.concatenate([k + [0, 1, 2], k + [0, 2, 3]]))
    v, f = _merged(np.concatenate(points), np.concatenate(faces))
    return _mesh(v * h, f)


def prism(polygon, kernel_point, levels) -> SurfaceMesh:
    """A prism over a counter-clockwise polygon (P, 2) with walls at the given z levels and
    caps fanned from ``kernel_point`` (any point that sees the whole polygon)."""
    poly = np.asarray(polygon, dtype=np.float64)
    p, m = len(poly), len(levels)
    ring = np.concatenate([np.column_stack([poly, np.full(p, z)]) for z in levels])
    centres = np.array([[*kernel_point, levels[0]], [*kernel_point, levels[-1]]])
    i = np.arange(p)
    walls = []
    for k in range(m - 1):
        a, b = k * p + i, k * p + (i + 1) % p
        c, d = b + p, a + p
        walls += [np.stack([a, b, c], 1), np.stack([a, c, d], 1)]
    bottom = np.stack([np.full(p, m * p), (i + 1) % p, i], 1)
    top = np.stack([np.full(p, m * p + 1), (m - 1) * p + i, (m - 1) * p + (i + 1) % p], 1)
    return _mesh(np.concatenate([ring, centres]), np.concatenate(walls + [bottom, top]))


def tube(outer, inner, levels) -> SurfaceMesh:
    """A hollow prism along z between two counter-clockwise rings of the same length (P, 2),
    point ``i`` of one facing point ``i`` of the other."""
    out_ring, in_ring = np.asarray(outer, dtype=np.float64), np.asarray(inner, dtype=np.float64)
    sides, m = len(out_ring), len(levels)
    out = np.concatenate([np.column_stack([out_ring, np.full(sides, z)]) for z in levels])
    inn = np.concatenate([np.column_stack([in_ring, np.full(sides, z)]) for z in levels])
    i = np.arange(sides)
    o = lambda k, j: k * sides + j % sides  # noqa: E731
    q = lambda k, j: m * sides + k * sides + j % sides  # noqa: E731
    faces = []
    for k in range(m - 1):
        a, b, c, d = o(k, i), o(k, i + 1), o(k + 1, i + 1), o(k + 1, i)
        faces += [np.stack([a, b, c], 1), np.stack([a, c, d], 1)]
        a, b, c, d = q(k, i), q(k, i + 1), q(k + 1, i + 1), q(k + 1, i)
        faces += [np.stack([a, c, b], 1), np.stack([a, d, c], 1)]
    t, b = m - 1, 0
    faces += [np.stack([o(t, i), o(t, i + 1), q(t, i + 1)], 1), np.stack([o(t, i), q(t, i + 1), q(t, i)], 1)]
    faces += [np.stack([o(b, i), q(b, i + 1), o(b, i + 1)], 1), np.stack([o(b, i), q(b, i), q(b, i + 1)], 1)]
    return _mesh(np.concatenate([out, inn]), np.concatenate(faces))


def circle(radius: float, sides: int) -> np.ndarray:
    t = 2 * np.pi * np.arange(sides) / sides
    return radius * np.column_stack([np.cos(t), np.sin(t)])


def square(half: float, per_side: int, centre=(0.0, 0.0)) -> np.ndarray:
    """``4 per_side`` points along a square's sides, counter-clockwise: rows of collinear points."""
    s = np.linspace(-half, half, per_side + 1)[:-1]
    low, high = np.full(per_side, -half), np.full(per_side, half)
    sides = [np.column_stack(p) for p in ((s, low), (high, s), (-s, high), (low, -s))]
    return np.concatenate(sides) + centre


def torus(big: float = 1.0, small: float = 0.4, nu: int = 96, nv: int = 48) -> SurfaceMesh:
    """A grid torus about z; rows of vertices lie exactly in z = 0 (v = 0 and v = pi)."""
    u, v = np.meshgrid(2 * np.pi * np.arange(nu) / nu, 2 * np.pi * np.arange(nv) / nv, indexing="ij")
    radius = big + small * np.cos(v)
    z = np.where(np.isclose(np.sin(v), 0.0, atol=1e-12), 0.0, small * np.sin(v))
    points = np.stack([radius * np.cos(u), radius * np.sin(u), z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    a, b = i * nv + j, (i + 1) % nu * nv + j
    c, d = (i + 1) % nu * nv + (j + 1) % nv, i * nv + (j + 1) % nv
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return _mesh(points, faces)


def icosphere(radius: float = 1.0, nsub: int = 4, centre=(0.0, 0.0, 0.0)) -> SurfaceMesh:
    import pyvista as pv

    s = pv.Icosphere(radius=radius, nsub=nsub, center=centre)
    return _mesh(s.points, s.regular_faces)


def heightfield(height, n: int, bottom: float = -1.0) -> SurfaceMesh:
    """A solid over [-1, 1]^2 between z = ``bottom`` and z = ``height(x, y)``, an n x n grid on top."""
    s = np.linspace(-1.0, 1.0, n + 1)
    x, y = np.meshgrid(s, s, indexing="ij")
    top = np.stack([x, y, height(x, y)], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
    faces = [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)]
    # the rim of the top, counter-clockwise seen from above, and the bottom below it
    k = np.arange(n)
    rim = np.concatenate([k * (n + 1), n * (n + 1) + k, (n - k) * (n + 1) + n, n - k])
    m = len(top)
    bottom_ring = np.column_stack([top[rim, :2], np.full(len(rim), bottom)])
    r = np.arange(len(rim))
    r1 = (r + 1) % len(rim)
    faces += [np.stack([rim[r], m + r, m + r1], 1), np.stack([rim[r], m + r1, rim[r1]], 1)]
    centre = m + len(rim)
    faces.append(np.stack([np.full(len(rim), centre), m + r1, m + r], 1))
    points = np.concatenate([top, bottom_ring, [[0.0, 0.0, bottom]]])
    return _mesh(points, np.concatenate(faces))


def combine(*meshes) -> SurfaceMesh:
    base = np.cumsum([0] + [m.vertex_count for m in meshes])
    return _mesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.faces + b for m, b in zip(meshes, base)]),
        np.concatenate([m.colors for m in meshes]),
    )


# ---------------------------------------------------------------------------
# independent references: per-triangle clipping in float64
# ---------------------------------------------------------------------------


def clipped_reference(mesh: SurfaceMesh, origin, normal) -> tuple[float, float]:
    """(volume below the plane, section area) of a closed mesh, by clipping each triangle exactly."""
    o, n = np.asarray(origin, dtype=np.float64), np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    tri = mesh.vertices.astype(np.float64)[mesh.faces] - o  # apex of every cone at the origin (on the plane)
    d = tri @ n
    volume = 0.0
    flux = 0.0
    whole = np.all(d <= 0, axis=1)
    a, b, c = tri[whole, 0], tri[whole, 1], tri[whole, 2]
    volume += np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6
    flux += (np.cross(b - a, c - a) @ n).sum() / 2
    for k in np.flatnonzero(~whole & np.any(d < 0, axis=1)):
        poly = []
        for i in range(3):
            p, q, dp, dq = tri[k, i], tri[k, (i + 1) % 3], d[k, i], d[k, (i + 1) % 3]
            if dp <= 0:
                poly.append(p)
            if (dp < 0 < dq) or (dq < 0 < dp):
                poly.append(p + dp / (dp - dq) * (q - p))
        for i in range(1, len(poly) - 1):
            a, b, c = poly[0], poly[i], poly[i + 1]
            volume += a @ np.cross(b, c) / 6
            flux += np.cross(b - a, c - a) @ n / 2
    return float(volume), float(-flux)


def polygon_area(points) -> float:
    p = np.asarray(points, dtype=np.float64)
    return 0.5 * float(np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1]))


def cap_edges_ok(piece: SurfaceMesh) -> bool:
    """Every edge on the rim of the caps (used by one cap face and one side face) is used exactly twice."""
    edges, counts = piece.edge_face_counts()
    return bool(np.all(counts == 2))


def check_cut(mesh, origin, normal, *, loops=None, holes=None, area=None, area_tol=1e-6, **kwargs):
    """Slice and check every invariant; returns (below, above)."""
    before = [a.copy() for a in (mesh.vertices, mesh.faces, mesh.normals, mesh.colors)]
    below, above = slice_mesh(mesh, origin, normal, **kwargs)
    for a, b in zip(before, (mesh.vertices, mesh.faces, mesh.normals, mesh.colors)):
        np.testing.assert_array_equal(a, b)  # input untouched
    volume_below, section = clipped_reference(mesh, origin, normal)
    total = mesh.volume()
    for piece in (below, above):
        if piece.face_count:
            assert piece.is_closed_manifold()
            assert cap_edges_ok(piece)
        assert piece.is_cap.shape == (piece.face_count,)
        assert piece.cap_colors.shape == (int(piece.is_cap.sum()), 3)
    assert below.volume() + above.volume() == pytest.approx(total, rel=1e-6)
    assert below.volume() == pytest.approx(volume_below, rel=1e-6, abs=1e-6 * abs(total))
    cap_area = below.stats["cap_area"]
    assert cap_area == pytest.approx(section, rel=1e-6, abs=1e-9)
    # the cap faces carry the section: their area, and they lie in the plane
    v = below.vertices.astype(np.float64)[below.faces[below.is_cap]]
    cap_faces_area = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    assert cap_faces_area == pytest.approx(section, rel=1e-6)
    n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
    if len(v):
        assert np.abs((v - origin) @ n).max() <= 1e-5 * np.ptp(mesh.vertices, axis=0).max()
        # caps face out of each part: +n below, -n above
        assert np.all(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]) @ n > -1e-12)
    if loops is not None:
        assert below.stats["section_loops"] == loops
    if holes is not None:
        assert below.stats["section_holes"] == holes
    if area is not None:
        assert cap_area == pytest.approx(area, rel=area_tol)
    return below, above


# ---------------------------------------------------------------------------
# analytic cases
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("height", [0.0, 0.3, -0.71])
def test_sphere_cap_is_the_section_circle(height):
    sphere = icosphere(1.0, 4)
    below, above = check_cut(sphere, (0, 0, height), (0, 0, 1), loops=1, holes=0)
    # the polyhedron lies between the sphere and the ball through its faces' planes
    v = sphere.vertices.astype(np.float64)[sphere.faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    inner = np.min(np.abs(np.einsum("ij,ij->i", v[:, 0], n / np.linalg.norm(n, axis=1, keepdims=True))))
    area = below.stats["cap_area"]
    assert np.pi * (inner**2 - height**2) <= area <= np.pi * (1.0 - height**2)


def test_tilted_plane_through_sphere():
    check_cut(icosphere(1.0, 3), (0.1, -0.2, 0.05), (0.3, 1.0, -0.6), loops=1, holes=0)


def test_torus_equator_is_an_annulus():
    t = torus()
    below, above = check_cut(t, (0, 0, 0), (0, 0, 1), loops=2, holes=1)
    # the rings are the torus vertices at v = 0 and v = pi: regular 96-gons of radius 1.4 and 0.6
    ring = lambda r: r**2 * 96 / 2 * np.sin(2 * np.pi / 96)  # noqa: E731
    assert below.stats["cap_area"] == pytest.approx(ring(1.4) - ring(0.6), rel=1e-6)


def test_torus_through_its_hole_gives_two_discs():
    t = torus()
    below, above = check_cut(t, (0, 0, 0), (1, 0, 0), loops=2, holes=0)
    assert below.stats["cap_area"] == pytest.approx(2 * np.pi * 0.4**2, rel=0.01)  # 48-gons of radius 0.4


def test_hollow_tube_across_its_axis_has_nested_rings():
    t = tube(circle(1.0, 40), circle(0.6, 40), [0.0, 0.5, 1.0])
    ring = lambda r: r**2 * 40 / 2 * np.sin(2 * np.pi / 40)  # noqa: E731
    check_cut(t, (0, 0, 0.3), (0, 0, 1), loops=2, holes=1, area=ring(1.0) - ring(0.6))
    # the cut through the middle ring of vertices, and a tilted cut across the axis
    check_cut(t, (0, 0, 0.5), (0, 0, 1), loops=2, holes=1, area=ring(1.0) - ring(0.6))
    check_cut(t, (0, 0, 0.5), (0.2, 0.1, 1.0), loops=2, holes=1)


def test_tube_in_a_tube_nests_three_deep():
    rings = combine(tube(circle(2.0, 32), circle(1.6, 32), [0, 1]), tube(circle(1.0, 32), circle(0.5, 32), [0, 1]))
    below, _ = check_cut(rings, (0, 0, 0.4), (0, 0, 1), loops=4, holes=2)


@pytest.mark.parametrize("centre", [(0.0, 0.0), (0.31, -0.17)])
def test_square_tube_with_collinear_rings(centre):
    # both rings are rows of exactly collinear points, and earcut bridges the hole to the outer ring
    shape = tube(square(1.0, 12), square(0.5, 12, centre), [0.0, 0.5, 1.0])
    below, _ = check_cut(shape, (0, 0, 0.2), (0, 0, 1), loops=2, holes=1, area=4.0 - 1.0)
    assert len(np.unique(below.faces[below.is_cap])) == below.stats["section_points"]
    check_cut(shape, (0, 0, 0.5), (0, 0, 1), loops=2, holes=1, area=4.0 - 1.0)


L_SHAPE = [(0, 0), (3, 0), (3, 1), (1, 1), (1, 2.5), (0, 2.5)]
STAR = [(np.cos(a) * r, np.sin(a) * r) for a, r in zip(np.pi / 2 + np.arange(10) * np.pi / 5, [1.0, 0.38] * 5)]


@pytest.mark.parametrize("polygon, kernel", [(L_SHAPE, (0.5, 0.5)), (STAR, (0.0, 0.0))])
def test_concave_prisms(polygon, kernel):
    shape = prism(polygon, kernel, [0.0, 0.5, 1.0])
    area = polygon_area(polygon)
    check_cut(shape, (0, 0, 0.25), (0, 0, 1), loops=1, holes=0, area=area)
    check_cut(shape, (0, 0, 0.5), (0, 0, 1), loops=1, holes=0, area=area)  # through a ring of vertices
    check_cut(shape, (0.3, 0.2, 0.5), (0, 1, 0.05), loops=None)  # across the prism: concave sections


def test_cut_through_vertices_and_along_edges():
    box = grid_box(4, 3, 2, 0.5)
    # along a grid plane: every section point is a vertex, every section segment a mesh edge
    below, above = check_cut(box, (0, 0, 0.5), (0, 0, 1), loops=1, holes=0, area=2.0 * 1.5)
    assert below.stats["snapped_vertices"] == 14
    assert below.vertex_count + above.vertex_count == box.vertex_count + 14  # no new vertex: the cut reuses them
    # a diagonal plane through vertices, cutting faces through their corners
    check_cut(box, (1.0, 0.5, 0.5), (1, -1, 0))
    # the box's own faces: one part is everything, the other empty
    top_below, top_above = slice_mesh(box, (0, 0, 1.0), (0, 0, 1))
    bottom_below, bottom_above = slice_mesh(box, (0, 0, 0.0), (0, 0, 1))
    assert top_above.face_count == 0 and bottom_below.face_count == 0
    for whole in (top_below, bottom_above):
        assert whole.face_count == box.face_count and whole.is_closed_manifold()
        assert whole.volume() == pytest.approx(box.volume())


def test_cut_through_a_saddle_vertex():
    # z = x^2 - y^2 on top: the plane z = 0 meets the top along both diagonals, which cross at
    # the centre vertex; below, the section is two sectors touching there, above, two wedges
    saddle = heightfield(lambda x, y: 0.5 + (x**2 - y**2) - 0.5, 12)
    below, above = slice_mesh(saddle, (0, 0, 0), (0, 0, 1))
    assert below.is_closed_manifold()
    assert below.stats["section_loops"] == 2 and below.stats["section_holes"] == 0
    volume_below, section = clipped_reference(saddle, (0, 0, 0), (0, 0, 1))
    assert below.volume() == pytest.approx(volume_below, rel=1e-6)
    assert below.stats["cap_area"] == pytest.approx(section, rel=1e-6) and section == pytest.approx(2.0, rel=1e-6)
    # the part above is two wedges meeting at the centre vertex: closed, each edge twice, but pinched there
    edges, counts = above.edge_face_counts()
    assert np.all(counts == 2) and above.shell_count() == 2
    assert below.volume() + above.volume() == pytest.approx(saddle.volume(), rel=1e-6)


def test_snap_takes_near_vertices_onto_the_plane():
    box = grid_box(4, 3, 2, 0.5)
    diagonal = float(np.linalg.norm(np.ptp(box.vertices, axis=0)))
    origin = (0, 0, 0.5 + 0.3e-6 * diagonal)  # just above a row of vertices, within the snap distance
    below, above = slice_mesh(box, origin, (0, 0, 1))
    assert below.stats["snapped_vertices"] == 14
    assert below.vertex_count + above.vertex_count == box.vertex_count + 14  # cut through the row, no sliver
    assert below.volume() + above.volume() == pytest.approx(box.volume(), rel=1e-6)
    # each half is off the exact cut by at most the snap distance times the section's area
    exact, section = clipped_reference(box, origin, (0, 0, 1))
    assert abs(below.volume() - exact) <= below.stats["snap_distance"] * section
    assert abs(below.volume() - exact) > 0
    # without snapping the plane cuts every wall just above the row
    below, above = slice_mesh(box, origin, (0, 0, 1), snap=0.0)
    assert below.stats["snapped_vertices"] == 0 and below.is_closed_manifold() and above.is_closed_manifold()
    assert below.volume() == pytest.approx(exact, rel=1e-6)


def test_collinear_section_vertices_all_stay_in_the_cap():
    # the sides of a grid box cut between vertex rows give rows of exactly collinear points,
    # which earcut leaves out of its triangles
    box = grid_box(8, 6, 4, 0.25)
    below, above = check_cut(box, (0, 0, 0.3), (0, 0, 1), loops=1, holes=0, area=2.0 * 1.5)
    caps = below.faces[below.is_cap]
    rim = np.setdiff1d(np.unique(caps), below.faces[~below.is_cap].ravel(), assume_unique=False)
    assert len(rim) == 0  # no cap vertex is missing from the sides (and the edge counts above hold)
    # every section point, on the vertical edges and on the diagonals, is a corner of a cap triangle
    assert len(np.unique(caps)) == below.stats["section_points"] == 4 * (8 + 6)


def test_several_disjoint_components():
    parts = combine(icosphere(0.5, 3, (-1.5, 0, 0)), torus(0.8, 0.3, 48, 24), icosphere(0.4, 3, (1.8, 0.2, 0.1)))
    below, above = check_cut(parts, (0, 0, 0.05), (0, 0, 1), loops=4, holes=1)
    assert below.shell_count() == 3 and above.shell_count() == 3


def test_new_vertices_interpolate_normals_and_colours():
    sphere = icosphere(1.0, 3)
    gradient = 0.5 + 0.25 * sphere.vertices  # a linear colour field: interpolation along an edge is exact
    v = sphere.vertices
    mesh = SurfaceMesh(v, sphere.faces, v / np.linalg.norm(v, axis=1, keepdims=True), gradient.astype(np.float32))
    below, above = slice_mesh(mesh, (0, 0, 0.2), (0, 0, 1))
    for piece in (below, above):
        np.testing.assert_allclose(piece.colors, 0.5 + 0.25 * piece.vertices, atol=1e-6)
        np.testing.assert_allclose(np.linalg.norm(piece.normals, axis=1), 1.0, atol=1e-5)
        radial = piece.vertices / np.linalg.norm(piece.vertices, axis=1, keepdims=True)
        cos = np.einsum("ij,ij->i", piece.normals, radial)
        assert cos.min() > 0.99
    np.testing.assert_array_equal(below.cap_colors, np.tile(np.float32(CAP_COLOR), (int(below.is_cap.sum()), 1)))


def test_cap_colour_given_or_from_the_model():
    model = wb.Point((0, 0, 0), 1.0, color=(0.2, 0.4, 0.9))
    mesh = wb.polygonize(model, cellsize=0.1)
    below, above = slice_mesh(mesh, (0, 0, 0), (0, 0, 1), cap_color=(1, 0, 0))
    assert below.is_cap.sum() > 0 and np.all(below.cap_colors == [1, 0, 0]) and np.all(above.cap_colors == [1, 0, 0])
    below, above = slice_mesh(mesh, (0, 0, 0), (0, 0, 1), model=model)
    np.testing.assert_allclose(below.cap_colors, np.tile([0.2, 0.4, 0.9], (int(below.is_cap.sum()), 1)), atol=1e-6)


def test_polygonized_model_vs_model_cut_by_a_box():
    model = wb.scenes.peanut()
    h = 0.05
    lo, hi = (np.asarray(b) for b in wb.linearize(model).bounds)
    height = 0.5 * (lo[2] + hi[2]) + 0.013
    mesh = wb.polygonize(model, cellsize=h)
    below, _ = check_cut(mesh, (0, 0, height), (0, 0, 1))
    # the half-space as a box whose top face (skeleton plus iso distance) lies in the plane
    radius, big = 0.2, 10.0
    top = height - wb.ISO_DISTANCE * radius
    half = wb.Box((0, 0, top - big), (big, big, big), radius)
    cut = wb.polygonize(model & half, cellsize=h)
    v = cut.vertices.astype(np.float64)[cut.faces]
    n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    flat = (np.abs(v[:, :, 2] - height).max(axis=1) < 0.25 * h) & (n[:, 2] > 0.999 * np.linalg.norm(n, axis=1))
    flat_area = 0.5 * np.linalg.norm(n[flat], axis=1).sum()
    # the rim of the cap: edges of one cap face only
    caps = below.faces[below.is_cap]
    edges = np.sort(np.concatenate([caps[:, [0, 1]], caps[:, [1, 2]], caps[:, [2, 0]]]), axis=1)
    rim, count = np.unique(edges, axis=0, return_counts=True)
    p = below.vertices.astype(np.float64)
    perimeter = np.linalg.norm(p[rim[count == 1, 0]] - p[rim[count == 1, 1]], axis=1).sum()
    assert 0 < below.stats["cap_area"] - flat_area <= perimeter * h  # the polygonizer rounds the crease off


def test_several_planes_cut_earlier_caps():
    sphere = icosphere(1.0, 3)
    planes = [((0, 0, 0.1), (0, 0, 1)), ((0.05, 0, 0), (1, 0, 0)), ((0, -0.1, 0), (0, 1, 0))]
    pieces = slice_mesh(sphere, planes=planes)
    assert len(pieces) == 8
    assert sum(p.volume() for p in pieces) == pytest.approx(sphere.volume(), rel=1e-6)
    for p in pieces:
        assert p.is_closed_manifold()
        assert p.cap_colors.shape == (int(p.is_cap.sum()), 3)
        # every cap face lies in one of the planes; every plane bounds every piece
        v = p.vertices.astype(np.float64)[p.faces[p.is_cap]].mean(axis=1)
        distance = np.stack([np.abs((v - o) @ (np.asarray(n) / np.linalg.norm(n))) for o, n in planes])
        assert distance.min(axis=0).max() < 1e-5
        assert np.all(np.bincount(distance.argmin(axis=0), minlength=3) > 0)


def test_results_do_not_depend_on_the_thread_split():
    t = torus(1.0, 0.4, 200, 100)
    one = slice_mesh(t, (0, 0.01, 0.05), (0.1, 0.2, 1.0), threads=1)
    two = slice_mesh(t, (0, 0.01, 0.05), (0.1, 0.2, 1.0), threads=2)
    for a, b in zip(one, two):
        for name in ("vertices", "faces", "normals", "colors", "is_cap", "cap_colors"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_plane_missing_the_mesh():
    sphere = icosphere(1.0, 2)
    below, above = slice_mesh(sphere, (0, 0, 5), (0, 0, 1))
    assert above.face_count == 0 and below.face_count == sphere.face_count and not below.is_cap.any()
    assert below.volume() == pytest.approx(sphere.volume())


def test_face_code_table_is_exhaustive():
    table = _kernels.face_codes()
    for s0 in (-1, 0, 1):
        for s1 in (-1, 0, 1):
            for s2 in (-1, 0, 1):
                s = (s0, s1, s2)
                code = int(table[9 * (s0 + 1) + 3 * (s1 + 1) + s2 + 1])
                if s == (0, 0, 0):
                    assert code == -1
                    continue
                kind, corner, flag = code & 3, (code >> 2) & 3, code >> 4
                if min(s) < 0 < max(s):
                    if 0 in s:
                        assert kind == _kernels.SPLIT_VERTEX and s[corner] == 0
                        assert flag == (s[(corner + 1) % 3] < 0)
                    else:
                        assert kind == _kernels.SPLIT_EDGES
                        assert s[corner] != s[(corner + 1) % 3] == s[(corner + 2) % 3]
                        assert flag == (s[corner] < 0)
                else:
                    assert kind == (_kernels.ABOVE if max(s) > 0 else _kernels.BELOW)


# ---------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------


def test_open_mesh_is_refused_with_caps_and_cut_without():
    sphere = icosphere(1.0, 2)
    faces = np.delete(sphere.faces, 7, axis=0)
    open_mesh = _mesh(sphere.vertices, faces)
    saved = open_mesh.faces.copy()
    with pytest.raises(wb.MeshError, match=r"edge \(\d+, \d+\).*open boundary"):
        slice_mesh(open_mesh, (0, 0, 0.5), (0, 0, 1))
    np.testing.assert_array_equal(open_mesh.faces, saved)
    below, above = slice_mesh(open_mesh, (0, 0, 0.5), (0, 0, 1), cap=False)
    assert below.face_count + above.face_count > open_mesh.face_count
    assert not below.is_cap.any() and not above.is_cap.any()


def test_flipped_face_is_refused():
    sphere = icosphere(1.0, 2)
    faces = sphere.faces.copy()
    faces[3] = faces[3, ::-1]
    with pytest.raises(wb.MeshError, match="run the same way"):
        slice_mesh(_mesh(sphere.vertices, faces), (0, 0, 0), (0, 0, 1))


@pytest.mark.parametrize(
    "origin, normal, message",
    [
        ((0, 0, np.nan), (0, 0, 1), "origin"),
        ((0, 0, 0), (0, np.nan, 1), "normal"),
        ((0, 0, 0), (0, 0, 0), "non-zero"),
        ((0, 0), (0, 0, 1), "origin"),
        ((0, 0, 0), "up", "3-vector"),
    ],
)
def test_bad_plane(origin, normal, message):
    sphere = icosphere(1.0, 1)
    with pytest.raises(wb.MeshError, match=message):
        slice_mesh(sphere, origin, normal)


def test_bad_mesh_arrays():
    sphere = icosphere(1.0, 1)
    bad = sphere.faces.copy()
    bad[2, 1] = sphere.vertex_count
    with pytest.raises(wb.MeshError, match="face 2"):
        slice_mesh(_mesh(sphere.vertices, bad), (0, 0, 0), (0, 0, 1))
    v = sphere.vertices.copy()
    v[5] = np.nan
    with pytest.raises(wb.MeshError, match="vertex 5"):
        slice_mesh(_mesh(v, sphere.faces), (0, 0, 0), (0, 0, 1))
    with pytest.raises(wb.MeshError, match="SurfaceMesh"):
        slice_mesh(sphere.vertices, (0, 0, 0), (0, 0, 1))
    with pytest.raises(wb.MeshError, match="snap"):
        slice_mesh(sphere, (0, 0, 0), (0, 0, 1), snap=-1.0)
    with pytest.raises(wb.MeshError, match="not both"):
        slice_mesh(sphere, (0, 0, 0), (0, 0, 1), planes=[((0, 0, 0), (0, 0, 1))])
