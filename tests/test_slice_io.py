"""Mesh files (warpblob.io._meshfile.load_mesh) and the ``warpblob slice`` command."""

from __future__ import annotations

import argparse
import os

import numpy as np
import pytest

import warpblob as wb
from warpblob.io._meshfile import load_mesh
from warpblob.slice import slice as slice_mesh
from warpblob.slice._command import add_slice_parser


@pytest.fixture(scope="module")
def ball():
    return wb.polygonize(wb.Point((0, 0, 0), 1.0, color=(0.9, 0.2, 0.1)), cellsize=0.1)


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply", ".vtk", ".vtp"])
def test_load_mesh_reads_what_pyvista_writes(ball, tmp_path, suffix):
    path = str(tmp_path / f"ball{suffix}")
    ball.to_pyvista().save(path)
    mesh = load_mesh(path)
    assert mesh.is_closed_manifold()  # STL's separate corners and OBJ's repeated positions are merged
    assert mesh.vertex_count == ball.vertex_count and mesh.face_count == ball.face_count
    assert mesh.volume() == pytest.approx(ball.volume(), rel=1e-6)
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-5)
    # normals point out, whether read from the file or made from the faces
    assert np.all(np.einsum("ij,ij->i", mesh.normals, mesh.vertices) > 0)
    below, above = slice_mesh(mesh, (0, 0, 0.05), (0, 0, 1))
    assert below.is_closed_manifold() and above.is_closed_manifold()


def test_load_mesh_colours_from_vtk(ball, tmp_path):
    path = str(tmp_path / "ball.vtp")
    ball.to_pyvista().save(path)
    mesh = load_mesh(path)
    order = np.lexsort(mesh.vertices.T)
    reference = np.lexsort(ball.vertices.T)
    written = (np.clip(ball.colors, 0, 1) * 255).astype(np.uint8) / 255  # to_pyvista stores bytes
    np.testing.assert_allclose(mesh.colors[order], written[reference], atol=1e-6)


def test_load_mesh_reads_usd(ball, tmp_path):

    path = wb.usd.save_mesh(ball, str(tmp_path / "ball.usda"))
    mesh = load_mesh(path)
    np.testing.assert_array_equal(mesh.faces, ball.faces)
    np.testing.assert_allclose(mesh.vertices, ball.vertices)


def test_load_mesh_errors(tmp_path):
    with pytest.raises(wb.SceneError, match="no such file"):
        load_mesh(str(tmp_path / "missing.stl"))
    with pytest.raises(wb.SceneError, match="unknown mesh file type '.xyz'"):
        load_mesh(str(tmp_path / "points.xyz"))
    junk = tmp_path / "junk.ply"
    junk.write_text("this is not a ply file\n")
    with pytest.raises(wb.SceneError, match="junk.ply"):
        load_mesh(str(junk))


def _run(argv) -> int:
    parser = argparse.ArgumentParser(prog="warpblob")
    parser.add_argument("--device", default=None)
    add_slice_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.func(args)


def test_command_slices_a_scene(tmp_path, capsys):
    out = tmp_path / "mug"
    assert _run(["slice", "mug", "--plane", "0,0,0,0,1,0", "--cellsize", "0.1", "--out", str(out), "--png"]) == 0
    text = capsys.readouterr().out
    assert "below" in text and "above" in text and text.count("closed 2-manifold: True") == 2
    assert (out / "below.usda").exists() and (out / "above.usda").exists()
    assert open(out / "slice.png", "rb").read(4) == b"\x89PNG"

    halves = [wb.usd.load_mesh(str(out / f"{name}.usda")) for name in ("below", "above")]
    assert all(h.is_closed_manifold() for h in halves)


def test_command_slices_a_mesh_file_by_two_planes(ball, tmp_path, capsys):
    path = str(tmp_path / "ball.stl")
    ball.to_pyvista().save(path)
    out = tmp_path / "pieces"
    assert _run(["slice", path, "--plane", "0,0,0,0,0,1", "--plane", "0,0,0,1,0,0", "--out", str(out)]) == 0
    assert sorted(os.listdir(out)) == [f"piece_{k}.usda" for k in range(4)]
    assert capsys.readouterr().out.count("closed 2-manifold: True") == 4


def test_command_errors(ball, tmp_path):
    with pytest.raises(SystemExit):
        _run(["slice", "mug", "--plane", "0,0,1", "--out", str(tmp_path)])
    with pytest.raises(wb.WarpblobError, match="unknown source"):
        _run(["slice", "no_such_scene", "--plane", "0,0,0,0,0,1", "--out", str(tmp_path)])
    path = str(tmp_path / "ball.stl")
    ball.to_pyvista().save(path)
    with pytest.raises(wb.WarpblobError, match="--cellsize is for scenes"):
        _run(["slice", path, "--plane", "0,0,0,0,0,1", "--cellsize", "0.1", "--out", str(tmp_path / "x")])
    with pytest.raises(wb.MeshError, match="non-zero"):
        _run(["slice", path, "--plane", "0,0,0,0,0,0", "--out", str(tmp_path / "y")])
