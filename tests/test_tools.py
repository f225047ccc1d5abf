"""Tools and paths: closed outward meshes with their analytic volumes, cutting edges and drill walls,
pose and slerp conventions against hand-computed rotations, travel alignment, and USD round trips
through stages authored with pxr directly."""

import math

import numpy as np
import pytest
import warp as wp

from warpblob import SceneError, ToolError
from warpblob.mesh import SurfaceMesh
from warpblob.tools import Drill, Path, Pose, Probe, Scalpel, Tool

TETRA_V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
TETRA_F = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


def axis_angle(axis, degrees):
    """Quaternion (x, y, z, w) of a rotation by ``degrees`` about ``axis``."""
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    half = math.radians(degrees) / 2
    return np.append(axis * math.sin(half), math.cos(half))


def rot(axis, degrees):
    """3x3 rotation matrix about a coordinate axis 'x', 'y' or 'z' (Rodrigues, written out)."""
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def same_rotation(q0, q1, atol=1e-9):
    """Quaternions q and -q are the same rotation."""
    q0, q1 = np.asarray(q0), np.asarray(q1)
    return np.allclose(q0, q1, atol=atol) or np.allclose(q0, -q1, atol=atol)


def random_rotations(count, seed=0):
    q = np.random.default_rng(seed).normal(size=(count, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ---------------------------------------------------------------- tool meshes


def polygon_area(n, radius):
    return 0.5 * n * radius**2 * math.sin(2 * math.pi / n)


TOOLS = {
    "probe": (lambda: Probe(0.7), 0.7**3),
    "scalpel": (lambda: Scalpel(2.0, 0.5, thickness=0.04), 2.0 * 0.5 * 0.04 / 2),
    "scalpel default": (lambda: Scalpel(1.0, 0.3), 1.0 * 0.3 * 0.03 / 2),
    "drill": (
        lambda: Drill(0.5, 2.0, segments=12, thickness=0.1),
        2.0 * (polygon_area(12, 0.55) - polygon_area(12, 0.45)),
    ),
    "drill default": (lambda: Drill(0.25, 1.0), 1.0 * (polygon_area(16, 0.2625) - polygon_area(16, 0.2375))),
}


@pytest.mark.parametrize("name", TOOLS)
def test_tool_is_closed_and_outward_with_analytic_volume(name):
    make, volume = TOOLS[name]
    tool = make()
    assert tool.is_closed()
    # an independent checker: the library's manifold test (edges twice, once each way, one fan per vertex)
    v = tool.vertices.astype(np.float32)
    assert SurfaceMesh(v, tool.faces, v, v).is_closed_manifold()
    assert tool.volume() > 0
    assert tool.volume() == pytest.approx(volume, rel=1e-12)
    assert tool.vertices.dtype == np.float64 and tool.faces.dtype == np.int32


@pytest.mark.parametrize("name", ["probe", "scalpel"])
def test_convex_tool_faces_point_away_from_the_centre(name):
    tool = TOOLS[name][0]()
    corners = tool.vertices[tool.faces]
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    outward = corners.mean(axis=1) - tool.vertices.mean(axis=0)
    assert np.all(np.einsum("ij,ij->i", normal, outward) > 0)


def test_probe_contact_face_is_at_the_local_origin():
    probe = Probe(2.0)
    assert np.array_equal(probe.bounds(), [[-1, -1, 0], [1, 1, 2]])
    assert np.count_nonzero(probe.vertices[:, 2] == 0) == 4
    assert repr(probe) == "Probe(size=2): 8 vertices, 12 triangles, volume 8"


def test_scalpel_edge_points_match_its_mesh():
    blade = Scalpel(3.0, 0.5, thickness=0.05)
    tip, heel = blade.edge
    assert np.array_equal(tip, [0, 0, 0]) and np.array_equal(heel, [0, 3, 0])
    # both ends are mesh vertices, joined by a mesh edge
    i, j = (int(np.flatnonzero((blade.vertices == p).all(axis=1))[0]) for p in blade.edge)
    directed = {(int(a), int(b)) for f in blade.faces for a, b in zip(f, np.roll(f, -1))}
    assert (i, j) in directed and (j, i) in directed
    # the edge is the sharp leading end: the vertices at the lowest z are exactly its two ends
    lowest = blade.vertices[blade.vertices[:, 2] == blade.vertices[:, 2].min()]
    assert sorted(map(tuple, lowest)) == sorted(map(tuple, blade.edge))
    assert blade.bounds()[1].tolist() == [0.025, 3.0, 0.5]
    # posed, singly and in a batch, the edge points follow the mesh vertices
    poses = Pose(np.random.default_rng(1).normal(size=(5, 3)), random_rotations(5))
    a, b = blade.edge_points(poses)
    world = blade.world_vertices(poses)
    assert a.shape == b.shape == (5, 3)
    assert np.allclose(a, world[:, i]) and np.allclose(b, world[:, j])
    a1, b1 = blade.edge_points(poses[2])
    assert np.allclose(a1, a[2]) and np.allclose(b1, b[2])
    assert np.allclose(np.linalg.norm(b - a, axis=1), 3.0)


def test_scalpel_on_a_horizontal_aligned_path_holds_its_edge_vertical():
    blade = Scalpel(2.0, 0.4)
    for direction in [(1, 0, 0), (0, -1, 0), (1, 1, 0)]:
        path = Path.line((0, 0, 0), direction, 1.0, align=True)
        tip, heel = blade.edge_points(path.pose(0.3))
        assert np.allclose(heel - tip, (0, 0, 2), atol=1e-12)
        # the blade trails the edge: every vertex is at or behind the edge along the travel
        d = np.asarray(direction) / np.linalg.norm(direction)
        along = (blade.world_vertices(path.pose(0.3)) - tip) @ d
        assert along.max() == pytest.approx(0.0, abs=1e-12) and along.min() == pytest.approx(-0.4)


def test_drill_wall_quads_lie_on_the_cylinder():
    drill = Drill(0.5, 2.0, segments=10)
    quads = drill.wall_quads()
    assert quads.shape == (10, 4, 3)
    assert np.allclose(np.linalg.norm(quads[..., :2], axis=-1), 0.5)
    assert np.array_equal(quads[:, :, 2], np.tile([0.0, 0.0, 2.0, 2.0], (10, 1)))
    # neighbouring quads share their side, and the band closes
    assert np.array_equal(quads[:, 1], np.roll(quads[:, 0], -1, axis=0))
    # corners counter-clockwise from outside: the normal points away from the axis
    normal = np.cross(quads[:, 1] - quads[:, 0], quads[:, 3] - quads[:, 0])
    assert np.all(np.einsum("ij,ij->i", normal, quads.mean(axis=1) * (1, 1, 0)) > 0)
    # the cut cylinder is the middle of the tube's wall
    radial = np.linalg.norm(drill.vertices[:, :2], axis=1)
    assert np.allclose(np.unique(radial.round(12)), [0.475, 0.525])
    # posed: every corner stays `radius` from the posed axis, and the bit end at the posed origin
    poses = Pose(np.random.default_rng(2).normal(size=(4, 3)), random_rotations(4, seed=3))
    world = drill.wall_quads(poses)
    assert world.shape == (4, 10, 4, 3)
    axis = poses.rotate([0, 0, 1])
    offset = world - poses.position[:, None, None]
    height = np.einsum("pqcj,pj->pqc", offset, axis)
    radial = offset - height[..., None] * axis[:, None, None]
    assert np.allclose(np.linalg.norm(radial, axis=-1), 0.5)
    assert np.allclose(height[:, :, :2], 0.0) and np.allclose(height[:, :, 2:], 2.0)


def test_sample_surface_covers_the_faces_at_the_spacing():
    probe = Probe(1.0)
    points = probe.sample_surface(0.1)
    # on the surface: every point is inside the box and on one of its six faces
    lo, hi = probe.bounds()
    assert np.all(points >= lo - 1e-12) and np.all(points <= hi + 1e-12)
    on_face = (np.abs(points - lo) < 1e-12) | (np.abs(points - hi) < 1e-12)
    assert on_face.any(axis=1).all()
    assert np.array_equal(points[:8], probe.vertices)
    assert len(np.unique(points.round(9), axis=0)) == len(points)
    gaps = np.linalg.norm(points[:, None] - points[None], axis=2)
    np.fill_diagonal(gaps, np.inf)
    assert gaps.min(axis=1).max() <= 0.1 + 1e-12
    # every face is reached: a fine grid of face points is never far from a sample
    u, w = np.meshgrid(np.linspace(-0.5, 0.5, 21), np.linspace(0, 1, 21))
    side = np.column_stack([u.ravel(), np.full(u.size, 0.5), w.ravel()])
    assert np.linalg.norm(side[:, None] - points[None], axis=2).min(axis=1).max() < 0.1
    # a batch of poses places the cached local samples
    poses = Path.line((0, 0, 0), (1, 2, 3), 1.0, align=True).pose(np.linspace(0, 1, 3))
    world = probe.sample_surface(0.1, pose=poses)
    assert world.shape == (3,) + points.shape
    assert np.allclose(world[1], poses[1].apply(points))
    assert probe.sample_surface(0.1) is not points  # a copy each call; the cache stays read-only


def test_sample_surface_of_a_scalpel_stays_on_the_blade():
    blade = Scalpel(1.0, 0.2, thickness=0.02)
    points = blade.sample_surface(0.05)
    x, y, z = points.T
    assert np.all((y >= -1e-12) & (y <= 1 + 1e-12) & (z >= -1e-12) & (z <= 0.2 + 1e-12))
    # within the wedge: |x| grows linearly from the edge to half the thickness at the back
    assert np.all(np.abs(x) <= 0.01 * z / 0.2 + 1e-12)


def test_tool_copies_its_inputs_and_is_read_only():
    v, f = TETRA_V.copy(), TETRA_F.copy()
    tool = Tool(v, f)
    v[0] = 9.0
    f[0] = (1, 2, 3)
    assert np.array_equal(tool.vertices, TETRA_V) and np.array_equal(tool.faces, TETRA_F)
    with pytest.raises(ValueError):
        tool.vertices[0, 0] = 1.0
    assert repr(tool) == "Tool: 4 vertices, 4 triangles, volume 0.166667"


def test_tool_pose_and_pyvista():
    probe = Probe(1.0)
    pose = Pose((1, 2, 3), axis_angle((0, 0, 1), 90))
    assert np.allclose(probe.bounds(pose), [[0.5, 1.5, 3.0], [1.5, 2.5, 4.0]])
    poly = probe.to_pyvista(pose)
    assert poly.n_points == 8 and poly.n_cells == 12
    assert poly.volume == pytest.approx(1.0)
    assert np.allclose(poly.points, probe.world_vertices(pose))
    assert probe.bounds(Pose(np.zeros((2, 3)))).shape == (2, 2, 3)
    with pytest.raises(ToolError, match="single pose"):
        probe.to_pyvista(Pose(np.zeros((2, 3))))
    with pytest.raises(ToolError, match="must be a warpblob.tools.Pose"):
        probe.world_vertices((1, 2, 3))


@pytest.mark.parametrize(
    "vertices, faces, message",
    [
        ([[0, 0, 0], [1, 0]], TETRA_F, r"vertices must be numbers of shape \(N, 3\)"),
        (np.vstack([TETRA_V[:3], [np.nan, 0, 1]]), TETRA_F, r"vertices\[3\] must be finite"),
        (TETRA_V, TETRA_F.astype(float), "faces must be integer"),
        (TETRA_V, TETRA_F[:, :2], r"faces must have shape \(F, 3\)"),
        (TETRA_V, TETRA_F[:3], "F >= 4"),
        (TETRA_V, np.where(TETRA_F == 3, 4, TETRA_F), r"faces\[1\] = \[0, 1, 4\] indexes outside the 4 vertices"),
        (TETRA_V, np.where(TETRA_F == 3, -1, TETRA_F), r"faces\[1\] = \[0, 1, -1\] indexes outside"),
        (TETRA_V, np.vstack([TETRA_F[:3], [0, 2, 2]]), r"face 3 \(0, 2, 2\) repeats a vertex"),
        (np.vstack([TETRA_V, [5, 5, 5]]), TETRA_F, "vertex 4 is used by no face"),
        (TETRA_V, np.vstack([TETRA_F[:3], TETRA_F[2]]), r"edge \(0, 2\) of face 0 runs 1 time\(s\) from 0 to 2 and 0"),
        (TETRA_V, np.vstack([TETRA_F[:1, ::-1], TETRA_F[1:]]), r"edge \(1, 2\) of face 0 runs 2 time\(s\)"),
        (TETRA_V, TETRA_F[:, ::-1], "encloses volume -0.166667: it must be positive"),
    ],
)
def test_tool_refuses_bad_meshes(vertices, faces, message):
    with pytest.raises(ToolError, match=message):
        Tool(vertices, faces)


def test_tool_refuses_an_open_mesh_naming_the_edge():
    cube = Probe(1.0)
    with pytest.raises(ToolError, match=r"edge \(\d+, \d+\) of face \d+ runs 1 time\(s\) from \d+ to \d+ and 0"):
        Tool(cube.vertices, cube.faces[1:])


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: Probe(0), "Probe: size must be positive, got 0"),
        (lambda: Probe(-1.0), "Probe: size must be positive, got -1.0"),
        (lambda: Probe(float("nan")), "Probe: size must be finite, got nan"),
        (lambda: Probe("big"), "Probe: size must be a number, got 'big'"),
        (lambda: Scalpel(0, 1), "Scalpel: length must be positive"),
        (lambda: Scalpel(1, float("inf")), "Scalpel: width must be finite"),
        (lambda: Scalpel(1, 1, thickness=0), "Scalpel: thickness must be positive"),
        (lambda: Drill(0, 1), "Drill: radius must be positive"),
        (lambda: Drill(1, -2), "Drill: length must be positive"),
        (lambda: Drill(1, 1, segments=2), "Drill: segments must be an integer >= 3, got 2"),
        (lambda: Drill(1, 1, segments=8.0), "Drill: segments must be an integer >= 3, got 8.0"),
        (lambda: Drill(1, 1, segments=True), "Drill: segments must be an integer >= 3, got True"),
        (lambda: Drill(1, 1, thickness=2.0), r"Drill: thickness must be less than 2 \* radius = 2, got 2.0"),
        (lambda: Probe(1).sample_surface(0), "Tool.sample_surface: spacing must be positive, got 0"),
        (lambda: Probe(1).sample_surface(float("nan")), "spacing must be finite"),
    ],
)
def test_tool_parameters_are_checked(make, message):
    with pytest.raises(ToolError, match=message):
        make()


# ---------------------------------------------------------------- poses


def test_pose_convention_rotate_then_translate():
    pose = Pose((1, 2, 3), axis_angle((0, 0, 1), 90))
    assert np.allclose(pose.apply([1, 0, 0]), [1, 3, 3])
    assert np.allclose(pose.rotate([1, 0, 0]), [0, 1, 0])
    m = pose.matrix()
    assert np.allclose(m, [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])
    points = np.random.default_rng(4).normal(size=(6, 3))
    assert np.allclose(pose.apply(points), points @ m[:3, :3].T + m[:3, 3])
    assert np.allclose(pose.inverse().apply(pose.apply(points)), points)
    assert np.allclose(pose.numpy(), [1, 2, 3, 0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)])
    assert repr(Pose()) == "Pose(position=(0, 0, 0), rotation=(0, 0, 0, 1))"


def test_pose_rotation_is_normalized_and_its_inputs_copied():
    q = np.array([0.0, 0.0, 2.0, 2.0])
    pose = Pose((0, 0, 0), q)
    q[:] = 0
    assert np.allclose(pose.rotation, axis_angle((0, 0, 1), 90))
    with pytest.raises(ValueError):
        pose.position[0] = 1.0


def test_pose_layout_is_warps_transform():
    poses = Pose(np.random.default_rng(5).normal(size=(3, 3)), random_rotations(3, seed=6))
    point = np.array([0.3, -1.2, 2.0])
    transforms = wp.array(poses.numpy(), dtype=wp.transform, device="cpu").numpy()
    for k in range(3):
        moved = wp.transform_point(wp.transform(*transforms[k].tolist()), wp.vec3(*point))
        assert np.allclose(np.array(moved), poses[k].apply(point), atol=1e-5)


def test_pose_batches_broadcast_and_index():
    poses = Pose(np.arange(6.0).reshape(2, 3))  # one rotation shared by both
    assert poses.shape == (2,) and len(poses) == 2 and poses.rotation.shape == (2, 4)
    assert poses.apply(np.zeros((5, 3))).shape == (2, 5, 3)
    assert np.array_equal(poses.apply([0, 0, 0]), np.arange(6.0).reshape(2, 3))
    assert np.array_equal(poses[1].position, [3, 4, 5]) and poses[1].shape == ()
    assert poses.matrix().shape == (2, 4, 4) and repr(poses) == "Pose: batch of 2"
    with pytest.raises(TypeError):
        len(Pose())


def test_pose_from_matrix_round_trips_every_quaternion_branch():
    # random rotations, plus half turns about each axis and the identity, where Shepperd's branches switch
    q = np.vstack([random_rotations(200, seed=7), np.eye(4)])
    poses = Pose(np.random.default_rng(8).normal(size=(len(q), 3)), q)
    back = Pose.from_matrix(poses.matrix())
    assert np.allclose(back.position, poses.position)
    assert np.allclose(np.abs(np.sum(back.rotation * poses.rotation, axis=1)), 1.0, atol=1e-12)
    assert np.all(back.rotation[:, 3] >= 0)
    one = Pose.from_matrix(poses[0].matrix())
    assert one.shape == () and same_rotation(one.rotation, poses.rotation[0])


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: Pose((0, 0)), r"Pose: position must have shape \(3,\) or \(N, 3\)"),
        (lambda: Pose((0, 0, np.nan)), "Pose: position must be finite"),
        (lambda: Pose(np.zeros((3, 3)), np.zeros((2, 4)) + 1), "Pose: 3 positions but 2 rotations"),
        (lambda: Pose((0, 0, 0), (0, 0, 0, 0)), r"Pose: rotation must be a non-zero quaternion \(x, y, z, w\)"),
        (lambda: Pose((0, 0, 0), [(0, 0, 0, 1), (0, 0, 0, 0)]), r"rotation\[1\] must be a non-zero quaternion"),
        (lambda: Pose((0, 0, 0), (0, 0, np.inf, 1)), "Pose: rotation must be finite"),
        (lambda: Pose((0, 0, 0), (0, 0, 1)), r"rotation must have shape \(4,\) or \(N, 4\)"),
        (lambda: Pose.from_matrix(np.eye(3)), r"matrix must have shape \(4, 4\) or \(N, 4, 4\)"),
        (lambda: Pose.from_matrix(np.diag([1, 1, 1.01, 1])), "matrix is not a rigid motion"),
        (lambda: Pose.from_matrix(np.diag([1, 1, -1, 1])), "matrix is not a rigid motion"),
        (lambda: Pose.from_matrix([np.eye(4), np.full((4, 4), np.nan)]), r"matrix\[1\] must be finite"),
        (lambda: Pose.along((0, 0, 0)), "Pose.along: direction must be non-zero"),
    ],
)
def test_pose_refuses_bad_input(make, message):
    with pytest.raises(ToolError, match=message):
        make()


# ---------------------------------------------------------------- paths


def test_path_slerp_midpoint_of_a_quarter_turn_is_an_eighth():
    path = Path([0.0, 2.0], [(0, 0, 0), (2, 4, 6)], [(0, 0, 0, 1), axis_angle((0, 0, 1), 90)])
    pose = path.pose(1.0)
    assert np.allclose(pose.position, [1, 2, 3])
    assert np.allclose(pose.rotation, [0, 0, math.sin(math.radians(22.5)), math.cos(math.radians(22.5))])
    assert np.allclose(pose.rotate([1, 0, 0]), [math.cos(math.pi / 4), math.sin(math.pi / 4), 0])
    # a quarter of the way in time is a quarter of the angle (constant angular speed)
    assert same_rotation(path.pose(0.5).rotation, axis_angle((0, 0, 1), 22.5))


def test_path_takes_the_shorter_arc():
    # -q is the same rotation as q: the path must still turn 90 degrees, not 270
    path = Path([0.0, 1.0], [(0, 0, 0)] * 2, [(0, 0, 0, 1), -axis_angle((0, 0, 1), 90)])
    assert same_rotation(path.pose(0.5).rotation, axis_angle((0, 0, 1), 45))
    assert np.all(np.sum(path.rotations[1:] * path.rotations[:-1], axis=1) >= 0)


def test_path_clamps_and_batches():
    path = Path([1.0, 2.0, 4.0], [(0, 0, 0), (1, 0, 0), (1, 2, 0)],
                [(0, 0, 0, 1), axis_angle((1, 0, 0), 60), axis_angle((0, 1, 0), 30)])  # fmt: skip
    assert np.array_equal(path.pose(-5.0).position, [0, 0, 0]) and np.array_equal(path.pose(9.0).position, [1, 2, 0])
    assert same_rotation(path.pose(9.0).rotation, path.rotations[-1])
    times = np.array([0.0, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0])
    batch = path.pose(times)
    assert batch.shape == (7,)
    for k, t in enumerate(times):
        one = path.pose(t)
        assert np.allclose(batch.position[k], one.position) and np.allclose(batch.rotation[k], one.rotation)
    assert np.allclose(batch.position[[2, 4]], [[0.5, 0, 0], [1, 1, 0]])
    assert np.allclose(path.pose(path.times).rotation, path.rotations)
    assert (path.t0, path.t1, path.duration, path.key_count) == (1.0, 4.0, 3.0, 3)
    assert repr(path) == "Path: 3 keys, t [1, 4] s, travel 3"


def test_path_velocity_and_direction():
    path = Path([0.0, 1.0, 3.0], [(0, 0, 0), (2, 0, 0), (2, 0, -4)])
    v = path.velocity(np.array([-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 3.5]))
    assert np.allclose(v, [[0, 0, 0], [2, 0, 0], [2, 0, 0], [0, 0, -2], [0, 0, -2], [0, 0, -2], [0, 0, 0]])
    assert np.allclose(path.direction(2.0), [0, 0, -1]) and np.array_equal(path.direction(5.0), [0, 0, 0])
    assert path.velocity(0.5).shape == (3,)
    still = Path([2.0], [(1, 2, 3)])
    assert np.array_equal(still.pose(7.0).position, [1, 2, 3]) and np.array_equal(still.velocity(2.0), [0, 0, 0])


DIRECTIONS = [(1, 0, 0), (0, 1, 0), (-1, -1, 0), (0, 0, -1), (0, 0, 1), (1, 2, 3), (0.3, 0, -5), (1e-9, 0, 1),
              (-2e-7, 1e-7, -1)]  # fmt: skip


@pytest.mark.parametrize("direction", DIRECTIONS)
def test_align_points_local_minus_z_along_the_travel(direction):
    d = np.asarray(direction, dtype=np.float64) / np.linalg.norm(direction)
    path = Path.line((1, 2, 3), np.add((1, 2, 3), direction), 2.0, align=True)
    pose = path.pose(1.0)
    assert np.allclose(pose.rotate([0, 0, -1]), d, atol=1e-12)
    assert np.allclose(path.direction(1.0), d)
    r = pose.rotation_matrix()
    assert np.allclose(r.T @ r, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)
    y = pose.rotate([0, 1, 0])
    if np.hypot(d[0], d[1]) > 1e-6:
        # roll: local +y as near world up as it can be, i.e. up's part perpendicular to the travel
        up = np.array([0, 0, 1.0]) - d[2] * d
        assert np.allclose(y, up / np.linalg.norm(up), atol=1e-9)
    else:
        assert np.allclose(y, [0, 1, 0], atol=1e-6)


def test_align_vertical_travel():
    down = Path.line((0, 0, 1), (0, 0, 0), 1.0, align=True).pose(0.5)
    assert np.array_equal(down.rotation, [0, 0, 0, 1])
    up = Path.line((0, 0, 0), (0, 0, 1), 1.0, align=True).pose(0.5)
    assert np.allclose(up.rotation_matrix(), rot("y", 180), atol=1e-12)
    # a drill driven up or down bores bit first: the bit (local z = 0) leads
    drill = Drill(0.1, 1.0)
    assert drill.bounds(down)[:, 2].tolist() == pytest.approx([0.5, 1.5])
    assert drill.bounds(up)[:, 2].tolist() == pytest.approx([-0.5, 0.5])


def test_line_without_align_keeps_the_identity():
    path = Path.line((0, 0, 0), (3, 0, 0), 1.5, t0=2.0)
    assert path.times.tolist() == [2.0, 3.5]
    assert np.array_equal(path.rotations, [[0, 0, 0, 1]] * 2)
    assert np.allclose(path.velocity(3.0), [2, 0, 0])


def test_polyline_times_and_aligned_corners():
    points = [(0, 0, 0), (4, 0, 0), (4, 0, -2), (4, 6, -2)]
    plain = Path.polyline(points, 2.0, t0=1.0)
    assert plain.times.tolist() == [1.0, 3.0, 4.0, 7.0]
    aligned = Path.polyline(points, 2.0, align=True, t0=1.0)
    assert aligned.key_count == 2 + 3 * 2
    # same route at the same constant speed
    t = np.linspace(1.0, 7.0, 61)
    assert np.allclose(aligned.pose(t).position, plain.pose(t).position)
    assert np.allclose(np.linalg.norm(aligned.velocity(t), axis=1), 2.0)
    # exactly aligned over the middle half of every segment (a quarter of the shorter neighbour each side)
    for lo, hi, d in [(1.0, 2.75, (1, 0, 0)), (3.25, 3.75, (0, 0, -1)), (4.25, 7.0, (0, 1, 0))]:
        forward = aligned.pose(np.linspace(lo, hi, 9)).rotate([0, 0, -1])
        assert np.allclose(forward, d, atol=1e-12)
    # at a corner, half-way through the turn
    q_in, q_out = Pose.along((1, 0, 0)).rotation, Pose.along((0, 0, -1)).rotation
    corner = aligned.pose(3.0)
    assert np.allclose(corner.position, [4, 0, 0])

    def angle(a, b):
        return 2 * math.acos(min(1.0, abs(float(np.dot(a, b)))))

    assert angle(corner.rotation, q_in) == pytest.approx(angle(q_in, q_out) / 2)
    assert angle(corner.rotation, q_out) == pytest.approx(angle(q_in, q_out) / 2)


def test_polyline_with_one_segment_is_a_line():
    a = Path.polyline([(0, 0, 0), (0, 3, 4)], 5.0, align=True)
    b = Path.line((0, 0, 0), (0, 3, 4), 1.0, align=True)
    assert np.allclose(a.times, b.times) and np.allclose(a.positions, b.positions)
    assert np.allclose(a.rotations, b.rotations)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: Path([0.0, 1.0, 1.0], np.zeros((3, 3))), r"strictly increasing, got times\[2\] = 1.0 after"),
        (lambda: Path([0.0, 2.0, 1.0], np.zeros((3, 3))), r"times\[2\] = 1.0 after times\[1\] = 2.0"),
        (lambda: Path([0.0, np.nan], np.zeros((2, 3))), r"times\[1\] must be finite, got nan"),
        (lambda: Path([], np.zeros((0, 3))), r"times must have shape \(N,\) with N >= 1"),
        (lambda: Path([[0.0, 1.0]], np.zeros((2, 3))), r"times must have shape \(N,\)"),
        (lambda: Path(["a"], np.zeros((1, 3))), "times must be numbers"),
        (lambda: Path([0.0, 1.0], [(0, 0, 0), (0, np.inf, 0)]), r"positions\[1\] must be finite, got \[0.0, inf, 0.0"),
        (lambda: Path([0.0, 1.0], np.zeros((2, 2))), r"positions must have shape \(N, 3\)"),
        (lambda: Path([0.0, 1.0], np.zeros((3, 3))), "2 times but 3 positions"),
        (lambda: Path([0.0, 1.0], np.zeros((2, 3)), [(0, 0, 0, 1)]), "2 times but 1 rotations"),
        (lambda: Path([0.0, 1.0], np.zeros((2, 3)), [(0, 0, 0, 1), (0, 0, 0, 0)]), r"rotations\[1\] must be a non"),
        (lambda: Path([0.0, 1.0], np.zeros((2, 3)), [(0, 0, 0, 1), (np.nan, 0, 0, 1)]), r"rotations\[1\] must be fin"),
        (lambda: Path([0.0, 1.0], np.zeros((2, 3)), np.eye(3)[:2]), r"rotations must have shape \(N, 4\)"),
        (lambda: Path.line((0, 0, 0), (1, 0, 0), 0.0), "Path.line: duration must be positive, got 0.0"),
        (lambda: Path.line((0, 0, 0), (1, 0, 0), -1), "Path.line: duration must be positive, got -1"),
        (lambda: Path.line((0, 0, 0), (1, 0, np.nan), 1), "Path.line: end must be finite"),
        (lambda: Path.line((0, 0, 0), [(1, 0, 0)], 1), r"Path.line: end must have shape \(3,\)"),
        (lambda: Path.line((0, 0, 0), (1, 0, 0), 1, t0=np.inf), "Path.line: t0 must be finite"),
        (lambda: Path.line((1, 1, 1), (1, 1, 1), 1, align=True), "align=True needs a direction, but start = end"),
        (lambda: Path.polyline([(0, 0, 0), (1, 0, 0)], 0), "Path.polyline: speed must be positive, got 0"),
        (lambda: Path.polyline([(0, 0, 0), (1, 0, 0)], -2.0), "speed must be positive, got -2.0"),
        (lambda: Path.polyline([(0, 0, 0)], 1), "points must have at least 2 rows, got 1"),
        (lambda: Path.polyline([(0, 0, 0), (1, 0, 0), (1, 0, 0)], 1), r"points\[1\] and points\[2\] coincide"),
        (lambda: Path.polyline([(0, 0, 0), (np.nan, 0, 0)], 1), r"points\[1\] must be finite"),
        (lambda: Path.line((0, 0, 0), (1, 0, 0), 1).pose(np.nan), "Path.pose: t must be finite"),
        (lambda: Path.line((0, 0, 0), (1, 0, 0), 1).pose(np.zeros((2, 2))), "Path.pose: t must be a number or"),
        (lambda: Path.line((0, 0, 0), (1, 0, 0), 1).velocity("now"), "Path.velocity: t must be a number or"),
    ],
)
def test_path_refuses_bad_input(make, message):
    with pytest.raises(ToolError, match=message):
        make()


# ---------------------------------------------------------------- USD


def _stage(fps):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    stage.SetTimeCodesPerSecond(fps)
    return stage


def test_from_usd_reads_translate_and_rotate_xyz_ops():
    from pxr import Gf, UsdGeom

    stage = _stage(24.0)
    xform = UsdGeom.Xform.Define(stage, "/World/Scalpel")
    translate = xform.AddTranslateOp()
    rotate = xform.AddRotateXYZOp()
    keys = {0: ((0, 0, 1), (0, 0, 0)), 12: ((1, 0, 1), (90, 0, 0)), 36: ((1, 2, 0), (10, 20, 30))}
    for code, (p, angles) in keys.items():
        translate.Set(Gf.Vec3d(*p), code)
        rotate.Set(Gf.Vec3f(*angles), code)
    path = Path.from_usd(stage, "/World/Scalpel")
    assert np.allclose(path.times, [0.0, 0.5, 1.5])
    for k, (p, (ax, ay, az)) in enumerate(keys.values()):
        pose = path.pose(path.times[k])
        # rotateXYZ turns about x first, then y, then z
        assert np.allclose(pose.rotation_matrix(), rot("z", az) @ rot("y", ay) @ rot("x", ax), atol=1e-7)
        assert np.allclose(pose.position, p)
    # between samples, positions interpolate linearly like USD's
    assert np.allclose(path.pose(0.25).position, [0.5, 0, 1])


def test_from_usd_reads_a_matrix_op_under_a_moved_parent_from_a_file(tmp_path):
    from pxr import Gf, UsdGeom

    stage = _stage(10.0)
    parent = UsdGeom.Xform.Define(stage, "/Rig")
    parent.AddTranslateOp().Set(Gf.Vec3d(0, 0, 5))
    drill = UsdGeom.Xform.Define(stage, "/Rig/Drill")
    op = drill.AddTransformOp()
    expected = {}
    keys = {3: ("x", 30, (1, 0, 0)), 5: ("y", -45, (0, 2, 0)), 9: ("z", 120, (3, 3, 3))}
    for code, (axis, degrees, p) in keys.items():
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = rot(axis, degrees), p
        # USD matrices act on row vectors: the transpose of the column-vector matrix
        op.Set(Gf.Matrix4d(m.T.tolist()), code)
        expected[code / 10.0] = (m[:3, :3], np.add(p, (0, 0, 5)))
    stage.SetDefaultPrim(parent.GetPrim())
    file = tmp_path / "drill.usda"
    stage.GetRootLayer().Export(str(file))
    read = [Path.from_usd(file, "/Rig/Drill"), Path.from_usd(str(file), "/Rig/Drill"), Path.from_usd(drill.GetPrim())]
    for path in read:
        assert np.allclose(path.times, list(expected))
        for t, (r, p) in expected.items():
            pose = path.pose(t)
            assert np.allclose(pose.rotation_matrix(), r, atol=1e-12) and np.allclose(pose.position, p)


def test_from_usd_keys_the_samples_of_animated_ancestors():
    from pxr import Gf, UsdGeom

    stage = _stage(4.0)
    arm = UsdGeom.Xform.Define(stage, "/Arm")
    swing = arm.AddRotateZOp()
    swing.Set(0.0, 0)
    swing.Set(90.0, 8)
    probe = UsdGeom.Xform.Define(stage, "/Arm/Probe")
    probe.AddTranslateOp().Set(Gf.Vec3d(1, 0, 0))  # static: every key comes from the arm
    path = Path.from_usd(stage, "/Arm/Probe")
    assert path.times.tolist() == [0.0, 2.0]
    assert np.allclose(path.positions, [(1, 0, 0), (0, 1, 0)])
    assert same_rotation(path.rotations[1], axis_angle((0, 0, 1), 90))


def test_to_usd_round_trip():
    from pxr import UsdGeom

    points = [(0, 0, 2), (1, 0, 1), (1, 1, 0), (0, 2, -1)]
    path = Path.polyline(points, 0.7, align=True, t0=0.5)
    stage = _stage(30.0)
    xform = path.to_usd(stage, "/World/Probe")
    assert [op.GetOpName() for op in xform.GetOrderedXformOps()] == ["xformOp:translate", "xformOp:orient"]
    assert xform.GetOrderedXformOps()[1].GetPrecision() == UsdGeom.XformOp.PrecisionDouble
    assert stage.GetStartTimeCode() == pytest.approx(15.0) and stage.GetEndTimeCode() == pytest.approx(path.t1 * 30)
    back = Path.from_usd(stage, "/World/Probe")
    assert np.allclose(back.times, path.times, rtol=0, atol=1e-12)
    assert np.allclose(back.positions, path.positions, atol=1e-12)
    assert all(same_rotation(a, b, atol=1e-12) for a, b in zip(back.rotations, path.rotations))
    # writing again replaces the samples, it does not merge them
    Path.line((5, 5, 5), (6, 5, 5), 1.0).to_usd(stage, "/World/Probe")
    again = Path.from_usd(stage.GetPrimAtPath("/World/Probe"))
    assert again.times.tolist() == [0.0, 1.0] and np.allclose(again.positions, [(5, 5, 5), (6, 5, 5)])
    assert stage.GetStartTimeCode() == 0.0


def test_from_usd_errors(tmp_path):
    from pxr import Gf, UsdGeom

    stage = _stage(24.0)
    UsdGeom.Scope.Define(stage, "/Group")
    UsdGeom.Xform.Define(stage, "/Still").AddTranslateOp().Set(Gf.Vec3d(1, 2, 3))
    grow = UsdGeom.Xform.Define(stage, "/Grow")
    grow.AddTranslateOp().Set(Gf.Vec3d(0, 0, 0), 0)
    scale = grow.AddScaleOp()
    scale.Set(Gf.Vec3f(1, 1, 1), 0)
    scale.Set(Gf.Vec3f(1, 1, 2), 24)
    with pytest.raises(SceneError, match="no such file"):
        Path.from_usd(tmp_path / "missing.usda")
    with pytest.raises(SceneError, match="no prim </Nowhere>"):
        Path.from_usd(stage, "/Nowhere")
    with pytest.raises(SceneError, match="prim </Group> is a Scope, not a UsdGeom.Xformable"):
        Path.from_usd(stage, "/Group")
    with pytest.raises(ToolError, match="</Still> has no time-sampled transform"):
        Path.from_usd(stage, "/Still")
    with pytest.raises(ToolError, match="</Grow> at time code 24 is not a rigid motion"):
        Path.from_usd(stage, "/Grow")
    with pytest.raises(ToolError, match="prim_path is for a stage or a file"):
        Path.from_usd(grow.GetPrim(), "/Grow")
    with pytest.raises(ToolError, match="source must be a Usd.Prim, a Usd.Stage or a file path, got 7"):
        Path.from_usd(7)


def test_to_usd_errors():
    stage = _stage(24.0)
    path = Path.line((0, 0, 0), (1, 0, 0), 1.0)
    with pytest.raises(ToolError, match="stage must be a Usd.Stage"):
        path.to_usd("scene.usda", "/Tool")
    with pytest.raises(SceneError, match="prim_path must be an absolute prim path"):
        path.to_usd(stage, "Tool")
    from pxr import UsdGeom

    UsdGeom.Scope.Define(stage, "/Group")
    with pytest.raises(SceneError, match="prim </Group> is a Scope, not Xformable"):
        path.to_usd(stage, "/Group")
