"""Thin walls: pinched boundaries of stuffed meshes are found, reported, warned about (or raised).

The eggshell is a shell between radii ``ISO_DISTANCE * 3.0`` and about
``1.181`` (0.18 thick): at cellsize 0.2 its boundary pinches. References: the
boundary faces and the manifold checks are recounted here in numpy, and the
shell's closed two-sphere boundary has Euler characteristic 4.
"""

import warnings

import numpy as np
import pytest

import warpblob as wb
from warpblob.tetrahedralize import PinchedBoundaryError, PinchedBoundaryWarning, tetrahedralize
from warpblob.tetrahedralize._pinch import find_pinches

SHELL = 0.181  # the eggshell's wall, model units (outer 1.362, inner 1.181)


def _manifold_defects(mesh):
    """(edges in more than two boundary faces, Euler characteristic V - E + F) of the boundary."""
    faces = mesh.surface_faces().astype(np.int64)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    vertices = np.unique(faces)
    return int(np.count_nonzero(counts > 2)), len(vertices) - len(unique) + len(faces)


def test_eggshell_at_a_coarse_cell_is_flagged_and_warned():
    with pytest.warns(PinchedBoundaryWarning, match=r"cellsize <= ([0-9.]+) resolves it"):
        mesh = tetrahedralize(wb.scenes.eggshell(), cellsize=0.2)
    s = mesh.stats
    over, _ = _manifold_defects(mesh)
    assert over > 0  # the independent count sees the pinch too
    assert s["pinched_edges"] == over and s["pinched_vertices"] > 0
    # the probe measures the wall: within 5% of the analytic thickness
    assert s["pinch_thickness"] == pytest.approx(SHELL, rel=0.05)
    assert s["pinch_cellsize"] < 0.2


def test_the_suggested_cellsize_resolves_the_eggshell():
    with pytest.warns(PinchedBoundaryWarning):
        coarse = tetrahedralize(wb.scenes.eggshell(), cellsize=0.2)
    with warnings.catch_warnings():
        warnings.simplefilter("error", PinchedBoundaryWarning)
        mesh = tetrahedralize(wb.scenes.eggshell(), cellsize=coarse.stats["pinch_cellsize"])
    assert mesh.stats["pinched_edges"] == 0 and mesh.stats["pinched_vertices"] == 0
    assert "pinch_cellsize" not in mesh.stats
    over, euler = _manifold_defects(mesh)
    assert over == 0 and euler == 4  # two closed spheres: the outer and the inner surface


def test_strict_raises():
    with pytest.raises(PinchedBoundaryError, match="pinched") as info:
        tetrahedralize(wb.scenes.eggshell(), cellsize=0.2, strict=True)
    assert isinstance(info.value, wb.WarpblobError)
    assert "0.2" in str(info.value)  # the offending cell size is named
    # a fine cell: nothing to raise
    mesh = tetrahedralize(wb.scenes.eggshell(), cellsize=0.08, strict=True)
    assert mesh.stats["pinched_edges"] == 0


def test_thick_models_are_not_flagged(device):
    with warnings.catch_warnings():
        warnings.simplefilter("error", PinchedBoundaryWarning)
        for name in ("tumor", "mug"):
            s = tetrahedralize(wb.scenes.ALL[name](), cellsize=0.1, device=device).stats
            assert s["pinched_edges"] == 0 and s["pinched_vertices"] == 0


def _tet_surface(a, b, c, d):
    return np.array([[a, c, b], [a, b, d], [a, d, c], [b, c, d]])


def test_find_pinches_on_hand_made_surfaces():
    one = _tet_surface(0, 1, 2, 3)
    edges, vertices = find_pinches(one)
    assert edges.shape == (0, 2) and vertices.size == 0
    # two tet surfaces sharing node 0 only: one pinched vertex
    edges, vertices = find_pinches(np.vstack([one, _tet_surface(0, 4, 5, 6)]))
    assert edges.shape == (0, 2) and vertices.tolist() == [0]
    # sharing edge (0, 1): a pinched edge (in four faces), its ends pinched vertices
    edges, vertices = find_pinches(np.vstack([one, _tet_surface(0, 1, 4, 5)]))
    assert edges.tolist() == [[0, 1]] and vertices.tolist() == [0, 1]
    # two separate closed surfaces: nothing
    edges, vertices = find_pinches(np.vstack([one, _tet_surface(4, 5, 6, 7)]))
    assert edges.shape == (0, 2) and vertices.size == 0
    # a double cone: two fans around node 0 glued only there
    fan = [[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]
    other = [[0, 4, 5], [0, 5, 6], [0, 6, 4], [4, 6, 5]]
    assert find_pinches(np.array(fan + other))[1].tolist() == [0]
