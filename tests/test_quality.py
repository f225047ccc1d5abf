"""Tet quality: analytic answers (regular, flattened, Kuhn tets) and a plain numpy reference."""

import numpy as np
import pytest
from test_tetmesh import cube_mesh, grid_mesh, positive, regular_tet

from warpblob.mesh._quality import ASPECT_RATIO_BINS, format_quality, quality
from warpblob.mesh._tetmesh import TET_EDGES, TetMesh

REGULAR_DIHEDRAL = np.degrees(np.arccos(1.0 / 3.0))  # 70.5288 degrees


def reference(nodes, tets):
    """Per-tet quality in float64 numpy, by other formulas than the kernel's.

    Dihedral angle at edge (a, b): the angle between the other two nodes
    projected onto the plane normal to the edge. Circumradius: the centre
    solves 2 (p_i - p_0) . x = |p_i|^2 - |p_0|^2.
    """
    p = np.asarray(nodes, dtype=np.float64)[np.asarray(tets)]
    volume = np.einsum("ij,ij->i", p[:, 1] - p[:, 0], np.cross(p[:, 2] - p[:, 0], p[:, 3] - p[:, 0])) / 6
    dihedral = np.zeros((len(p), 6))
    for j, (a, b) in enumerate(TET_EDGES):
        c, d = TET_EDGES[5 - j]
        axis = p[:, b] - p[:, a]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        u, v = p[:, c] - p[:, a], p[:, d] - p[:, a]
        u -= np.einsum("ij,ij->i", u, axis)[:, None] * axis
        v -= np.einsum("ij,ij->i", v, axis)[:, None] * axis
        cosine = np.einsum("ij,ij->i", u, v) / np.linalg.norm(u, axis=1) / np.linalg.norm(v, axis=1)
        dihedral[:, j] = np.degrees(np.arccos(np.clip(cosine, -1, 1)))
    lhs = 2 * (p[:, 1:] - p[:, :1])
    rhs = (p[:, 1:] ** 2).sum(axis=2) - (p[:, :1] ** 2).sum(axis=2)
    centre = np.linalg.solve(lhs, rhs[..., None])[..., 0]
    circumradius = np.linalg.norm(centre - p[:, 0], axis=1)
    faces = [(1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)]
    area = sum(0.5 * np.linalg.norm(np.cross(p[:, b] - p[:, a], p[:, c] - p[:, a]), axis=1) for a, b, c in faces)
    inradius = 3 * np.abs(volume) / area
    lengths = np.stack([np.linalg.norm(p[:, b] - p[:, a], axis=1) for a, b in TET_EDGES], axis=1)
    return volume, dihedral, circumradius / (3 * inradius), lengths


def test_regular_tet_is_analytic(device):
    q = quality(regular_tet(2.0), device=device)
    np.testing.assert_allclose(q.tet_dihedral, REGULAR_DIHEDRAL, rtol=1e-6)
    assert q.dihedral_min == pytest.approx(70.5288, abs=1e-4) and q.dihedral_max == pytest.approx(70.5288, abs=1e-4)
    assert q.aspect_ratio_min == pytest.approx(1.0, rel=1e-6) and q.aspect_ratio_max == pytest.approx(1.0, rel=1e-6)
    assert q.volume == pytest.approx(2.0**3 / (6 * np.sqrt(2)), rel=1e-6)
    np.testing.assert_allclose([q.tet_edge_min[0], q.tet_edge_max[0]], 2.0, rtol=1e-6)
    assert q.edge_ratio == pytest.approx(1.0, rel=1e-6) and q.volume_ratio == 1.0 and q.inverted_count == 0


def test_flattened_tets_get_worse():
    base = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float64)
    previous_min, previous_beta = 90.0, 1.0
    for height in (0.5, 0.1, 0.01, 0.001):
        nodes = np.vstack([base, [0.3, 0.3, height]])
        q = quality(TetMesh(nodes, positive(nodes, [[0, 1, 2, 3]])))
        assert q.dihedral_min < previous_min and q.aspect_ratio_max > previous_beta
        previous_min, previous_beta = q.dihedral_min, q.aspect_ratio_max
    assert previous_min < 1.0 and previous_beta > 1e3 and q.dihedral_max > 179.0


def test_flat_and_inverted_tets():
    nodes = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.3, 0.3, 0], [0, 0, 1]], dtype=np.float32)
    q = quality(TetMesh(nodes, [[0, 1, 2, 3], [0, 2, 1, 4]]))
    assert q.tet_volume[0] == 0 and q.tet_aspect_ratio[0] == np.inf and q.volume_ratio == np.inf
    assert q.tet_volume[1] < 0 and q.inverted_count == 2
    # the shape of an inverted tet is still measured
    assert np.isfinite(q.tet_aspect_ratio[1]) and q.tet_aspect_ratio[1] > 1


def test_kuhn_grid_summary_is_analytic():
    # every tet of the grid is the same Kuhn tet: edges 1, sqrt(2), sqrt(3); dihedral angles 45 (twice),
    # 60 (at the cube's diagonal, which six tets share) and 90 (three times)
    q = quality(grid_mesh(4))
    assert q.tet_count == 6 * 64 and q.node_count == 125
    assert q.volume == pytest.approx(1.0, rel=1e-6) and q.volume_ratio == pytest.approx(1.0, rel=1e-5)
    assert q.edge_ratio == pytest.approx(np.sqrt(3), rel=1e-6)
    assert q.dihedral_min == pytest.approx(45.0, abs=1e-4) and q.dihedral_max == pytest.approx(90.0, abs=1e-4)
    np.testing.assert_allclose(np.sort(q.tet_dihedral, axis=1)[0], [45, 45, 60, 90, 90, 90], atol=1e-4)
    assert q.aspect_ratio_min == pytest.approx(q.aspect_ratio_max, rel=1e-5)


def test_kernel_matches_numpy_reference(device):
    rng = np.random.default_rng(7)
    mesh = grid_mesh(11)  # 7986 tets: the CPU launch is split across threads
    jitter = rng.uniform(-0.02, 0.02, mesh.nodes.shape)
    nodes = (mesh.nodes + jitter).astype(np.float32)
    extra = rng.normal(size=(200, 4, 3)).astype(np.float32)  # random tets, some nearly flat, some inverted
    nodes = np.vstack([nodes, extra.reshape(-1, 3)])
    tets = np.vstack([mesh.tets, mesh.node_count + np.arange(800).reshape(200, 4)])
    q = quality(TetMesh(nodes, tets), device=device)
    volume, dihedral, beta, lengths = reference(nodes, tets)
    np.testing.assert_allclose(q.tet_volume, volume, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(q.tet_dihedral, dihedral, atol=1e-5)
    np.testing.assert_allclose(q.tet_dihedral_min, dihedral.min(axis=1), atol=1e-5)
    np.testing.assert_allclose(q.tet_dihedral_max, dihedral.max(axis=1), atol=1e-5)
    np.testing.assert_allclose(q.tet_aspect_ratio, beta, rtol=1e-6)
    np.testing.assert_allclose(q.tet_edge_min, lengths.min(axis=1), rtol=1e-12)
    np.testing.assert_allclose(q.tet_edge_max, lengths.max(axis=1), rtol=1e-12)
    np.testing.assert_allclose(q.tet_edge_ratio, lengths.max(axis=1) / lengths.min(axis=1), rtol=1e-12)
    assert q.edge_ratio == pytest.approx(lengths.max() / lengths.min())
    assert q.volume_ratio == pytest.approx(np.abs(volume).max() / np.abs(volume).min())
    assert q.inverted_count == np.count_nonzero(volume <= 0)
    counts, edges = q.dihedral_histogram
    assert counts.sum() == 6 * len(tets) and edges[0] == 0 and edges[-1] == 180
    counts, edges = q.aspect_ratio_histogram
    assert counts.sum() == len(tets)
    np.testing.assert_array_equal(edges, ASPECT_RATIO_BINS)
    np.testing.assert_array_equal(counts, np.histogram(beta, ASPECT_RATIO_BINS)[0])


def test_split_launch_matches_single_thread():
    mesh = grid_mesh(9)
    one, many = quality(mesh, threads=1), quality(mesh, threads=2)
    np.testing.assert_array_equal(one.tet_dihedral, many.tet_dihedral)
    np.testing.assert_array_equal(one.tet_aspect_ratio, many.tet_aspect_ratio)


def test_empty_mesh_summary_is_nan():
    q = quality(TetMesh(np.zeros((0, 3)), np.zeros((0, 4), dtype=int)))
    assert q.tet_count == 0 and np.isnan(q.dihedral_min) and np.isnan(q.aspect_ratio_max) and q.volume == 0


def test_cached_on_the_mesh_and_summary():
    mesh = cube_mesh()
    assert mesh.quality() is mesh.quality()
    summary = mesh.quality().summary()
    assert summary["tet_count"] == 5 and summary["node_count"] == 8
    assert summary["aspect_ratio_min"] == pytest.approx(1.0, rel=1e-6)  # the central regular tet
    assert summary["volume"] == pytest.approx(1.0)
    assert set(summary) >= {"dihedral_min", "dihedral_max", "volume_ratio", "edge_ratio", "aspect_ratio_max"}


def test_format_quality_report():
    text = format_quality(cube_mesh().quality())
    lines = text.splitlines()
    assert lines[0] == "tets 5  nodes 8  volume 1"
    assert "Vmax/Vmin             2" in text and "lmax/lmin             1.414" in text
    assert "min 1 " in text and "(1 = regular tet)" in text and "inverted tets         0" in text
    assert "dihedral angles (deg):" in text and "aspect ratio (beta):" in text
    assert len(lines) == 7 + 18 + 1 + len(ASPECT_RATIO_BINS) - 1


def test_repr_is_a_short_summary():
    # Kuhn's six tets of a cube have dihedral angles of 45, 60 and 90 degrees only
    q = grid_mesh(4).quality()
    text = repr(q)
    assert len(text) < 400 and len(text.splitlines()) <= 4
    assert f"{q.tet_count:,} tets" in text and f"{q.node_count:,} nodes" in text
    assert "dihedral angles [45.00, 90.00] deg" in text and "inverted tets 0" in text
    cube = cube_mesh()
    flipped = TetMesh(cube.nodes, np.concatenate([cube.tets[:1, [0, 2, 1, 3]], cube.tets[1:]]))
    assert "inverted tets 1" in repr(flipped.quality())
    assert "0 tets" in repr(quality(TetMesh(np.zeros((0, 3)), np.zeros((0, 4), dtype=int))))
