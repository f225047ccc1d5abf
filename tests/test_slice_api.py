"""The slicer as the package exposes it: ``wb.slice``, ``wb.load_mesh``, ``SurfaceMesh.slice``, ``warpblob slice``."""

from __future__ import annotations

import numpy as np

import warpblob as wb
from warpblob.cli import main


def test_top_level_and_method_agree():
    mesh = wb.polygonize(wb.scenes.mug(), cellsize=0.1)
    below, above = wb.slice(mesh, (0, 0, 0), (0, 1, 0))
    same = mesh.slice((0, 0, 0), (0, 1, 0))
    for a, b in zip((below, above), same):
        np.testing.assert_array_equal(a.faces, b.faces)
        np.testing.assert_array_equal(a.is_cap, b.is_cap)
        assert a.is_closed_manifold()
    pieces = mesh.slice(planes=[((0, 0, 0), (0, 1, 0)), ((0, 0, 1.4), (0, 0, 1))])
    assert len(pieces) == 4 and all(p.is_closed_manifold() for p in pieces)
    assert "slice" in wb.__all__ and "load_mesh" in wb.__all__


def test_load_mesh_at_the_top(tmp_path):
    mesh = wb.polygonize(wb.Point((0, 0, 0), 1.0), cellsize=0.2)
    path = str(tmp_path / "ball.ply")
    mesh.to_pyvista().save(path)
    assert wb.load_mesh(path).is_closed_manifold()


def test_cli_slice(tmp_path, capsys):
    out = tmp_path / "halves"
    assert main(["slice", "peanut", "--plane", "0,0,0,1,0,0", "--cellsize", "0.2", "--out", str(out)]) == 0
    assert capsys.readouterr().out.count("closed 2-manifold: True") == 2
    assert main(["slice", "peanut", "--plane", "0,0,0,0,0,0", "--out", str(out)]) == 1
    assert "normal must be non-zero" in capsys.readouterr().err
