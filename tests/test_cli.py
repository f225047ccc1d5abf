"""The ``warpblob`` command: subcommands, outputs and error paths (run as subprocesses)."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import warpblob as wb
import warpblob.usd


def run_cli(*args, cwd=None):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run(
        [sys.executable, "-m", "warpblob.cli", *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=600
    )


def test_help_lists_subcommands():
    r = run_cli("--help")
    assert r.returncode == 0
    for name in ("demo", "info", "field"):
        assert name in r.stdout


def test_info_matches_linearize():
    r = run_cli("info", "tumor", "--json")
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    lm = wb.linearize(wb.scenes.tumor())
    assert (info["primitives"], info["operators"], info["depth"]) == (lm.primitive_count, lm.operator_count, lm.depth)
    assert info["nbytes"] == lm.nbytes


def test_field_writes_values(tmp_path):
    pts = np.random.default_rng(0).uniform(-2, 2, (500, 3)).astype(np.float32)
    np.save(tmp_path / "pts.npy", pts)
    out = tmp_path / "f.npy"
    r = run_cli("field", "peanut", "--points", str(tmp_path / "pts.npy"), "--out", str(out))
    assert r.returncode == 0, r.stderr
    np.testing.assert_array_equal(np.load(out), wb.field(wb.scenes.peanut(), pts))
    assert not any(p.name.endswith(".tmp.npy") for p in tmp_path.iterdir())


@pytest.mark.parametrize(
    "args, words",
    [
        (("info", "no_such_scene"), "unknown scene 'no_such_scene'"),
        (("field", "tumor", "--points", "missing.npy"), "missing.npy"),
        (("--device", "cuda:7", "info", "tumor"), None),
        (("demo", "--resolution", "2"), "--resolution"),
    ],
)
def test_errors_are_one_line(tmp_path, args, words):
    r = run_cli(*args, cwd=tmp_path)
    if words is None:  # info does not touch the device: it must still succeed
        assert r.returncode == 0, r.stderr
        return
    assert r.returncode != 0
    assert "Traceback" not in r.stderr
    assert words in r.stderr
    assert len([line for line in r.stderr.splitlines() if line.startswith("warpblob")]) == 1


def test_field_rejects_bad_points(tmp_path):
    np.save(tmp_path / "bad.npy", np.zeros((4, 2)))
    r = run_cli("field", "tumor", "--points", str(tmp_path / "bad.npy"))
    assert r.returncode == 1
    assert "(4, 2)" in r.stderr and "Traceback" not in r.stderr


def test_field_bad_device(tmp_path):
    np.save(tmp_path / "p.npy", np.zeros((4, 3)))
    r = run_cli("--device", "cuda:7", "field", "tumor", "--points", str(tmp_path / "p.npy"))
    assert r.returncode == 1
    assert "cuda:7" in r.stderr and "Traceback" not in r.stderr


def test_demo_writes_stage_pictures_and_summary(tmp_path):
    out = tmp_path / "new" / "out"  # missing folders are made
    r = run_cli(
        "demo", "--out", str(out), "--scene", "peanut", "--resolution", "64", "--cellsize", "0.1", "--samples", "50000"
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["peanut"]["primitives"] == 2
    assert 0.0 < summary["peanut"]["inside_fraction"] < 1.0
    poly, mc = summary["peanut"]["polygonize"], summary["peanut"]["volume_monte_carlo"]
    assert poly["closed_manifold"] is True and poly["shells"] == 1  # two blended points: one solid
    assert mc["samples"] == 50000 and abs(poly["volume"] - mc["volume"]) < 4 * mc["standard_error"]
    text = (out / "summary.txt").read_text()
    assert "50,000 points" in text and "shells" in text
    for name in ("peanut_slices.png", "peanut_mesh.png"):
        png = (out / name).read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(out / "warpblob_demo.usdc"))
    assert UsdGeom.GetStageUpAxis(stage) == "Z" and stage.GetDefaultPrim().GetName() == "Demo"
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Demo/peanut/surface"))
    assert len(mesh.GetFaceVertexIndicesAttr().Get()) == 3 * summary["peanut"]["polygonize"]["triangles"]
    assert not any(".tmp" in p.name for p in out.iterdir())


def test_polygonize_writes_a_usd_mesh(tmp_path):
    out = tmp_path / "tumor.usda"
    r = run_cli("polygonize", "tumor", "--cellsize", "0.1", "--out", str(out), "--png", str(tmp_path / "t.png"))
    assert r.returncode == 0, r.stderr
    mesh = wb.usd.load_mesh(out)
    direct = wb.polygonize(wb.scenes.tumor(), cellsize=0.1)
    assert mesh.face_count == direct.face_count and mesh.is_closed_manifold()
    np.testing.assert_allclose(mesh.vertices, direct.vertices, atol=1e-6)
    assert (tmp_path / "t.png").stat().st_size > 5000
    # --no-relax keeps the vertices on their grid edges
    r = run_cli("polygonize", "tumor", "--cellsize", "0.1", "--out", str(out), "--no-relax")
    assert r.returncode == 0, r.stderr
    plain = wb.polygonize(wb.scenes.tumor(), cellsize=0.1, relax=False)
    np.testing.assert_allclose(wb.usd.load_mesh(out).vertices, plain.vertices, atol=1e-6)


@pytest.mark.parametrize(
    "args, words",
    [
        (("--cellsize", "-1", "--out", "m.usda"), "cellsize"),
        (("--cellsize", "0.1", "--out", "m.obj"), "m.obj"),
        (("--cellsize", "0.1", "--out", "a_file/m.usda"), "is a file"),
    ],
)
def test_polygonize_errors(tmp_path, args, words):
    (tmp_path / "a_file").write_text("")
    r = run_cli("polygonize", "tumor", *args, cwd=tmp_path)
    assert r.returncode == 1 and "Traceback" not in r.stderr and words in r.stderr
    assert not list(tmp_path.rglob("*.usda"))


def test_polygonize_makes_missing_folders(tmp_path):
    out = tmp_path / "meshes" / "tumor" / "m.usdc"
    png = tmp_path / "pictures" / "t.png"
    r = run_cli("polygonize", "tumor", "--cellsize", "0.2", "--out", str(out), "--png", str(png))
    assert r.returncode == 0, r.stderr
    assert wb.usd.load_mesh(out).is_closed_manifold() and png.stat().st_size > 5000


# every subcommand that writes: a bad output path next to a scene that does not exist. The error
# must name the output, so the outputs were checked before the scene was even looked up.
BAD_OUTPUTS = [
    (("demo", "--out", "a_file"), "is a file, not a folder"),
    (("demo", "--out", "a_file/pictures"), "is a file, so no folder"),
    (("demo", "--scene", "no_such_scene", "--out", "x"), "--scene must be"),
    (("polygonize", "no_such_scene", "--cellsize", "0.1", "--out", "m.obj"), "--out must be a .usda, .usdc, .usd file"),
    (("polygonize", "no_such_scene", "--cellsize", "0.1", "--out", "a_file/m.usda"), "is a file"),
    (("polygonize", "no_such_scene", "--cellsize", "0.1", "--out", "a_folder.usda"), "is a folder"),
    (("polygonize", "no_such_scene", "--cellsize", "0.1", "--out", "m.usda", "--png", "m.jpg"), "--png must be a .png"),
    (("tetrahedralize", "no_such_scene", "--cellsize", "0.1", "--out", "v.vtk"), "--out must be"),
    (("tetrahedralize", "no_such_scene", "--cellsize", "0.1", "--out", "a_file/v.usda"), "is a file"),
    (("field", "no_such_scene", "--points", "missing.npy", "--out", "f.txt"), "--out must be a .npy file"),
    (("field", "no_such_scene", "--points", "missing.npy", "--out", "a_file/f.npy"), "is a file"),
]


@pytest.mark.parametrize("args, words", BAD_OUTPUTS, ids=[" ".join(a) for a, _ in BAD_OUTPUTS])
def test_outputs_are_checked_before_any_work(tmp_path, args, words):
    (tmp_path / "a_file").write_text("")
    (tmp_path / "a_folder.usda").mkdir()
    before = sorted(p.name for p in tmp_path.rglob("*"))
    r = run_cli(*args, cwd=tmp_path)
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert words in r.stderr and "unknown scene" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written, no folder made


def test_unwritable_output_folder_is_refused(tmp_path, monkeypatch, capsys):
    """os.access stands in for a read-only folder (the tests may run as root, who can write anywhere)."""
    from warpblob import cli

    monkeypatch.setattr(cli.os, "access", lambda path, mode: os.path.abspath(path) != str(tmp_path))
    for args in (
        ["demo", "--out", str(tmp_path / "out")],
        ["polygonize", "no_such_scene", "--cellsize", "0.1", "--out", str(tmp_path / "m.usda")],
        ["field", "no_such_scene", "--points", "p.npy", "--out", str(tmp_path / "f.npy")],
    ):
        assert cli.main(args) == 1
        err = capsys.readouterr().err
        assert "is not writable" in err and str(tmp_path) in err
    assert list(tmp_path.iterdir()) == []


def test_info_and_field_read_usd_scenes(tmp_path):
    scene = os.path.join(os.path.dirname(__file__), "..", "usd_scenes", "tumor.usda")
    r = run_cli("info", scene, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["primitives"] == 10
    pts = np.random.default_rng(1).uniform(-2, 2, (300, 3)).astype(np.float32)
    np.save(tmp_path / "p.npy", pts)
    r = run_cli("field", scene, "--points", str(tmp_path / "p.npy"), "--out", str(tmp_path / "f.npy"))
    assert r.returncode == 0, r.stderr
    np.testing.assert_allclose(np.load(tmp_path / "f.npy"), wb.field(wb.scenes.tumor(), pts), atol=1e-6)


@pytest.mark.parametrize("content, words", [(None, "scene.usda: no such file"), ("#usda 1.0\n(\n", "scene.usda")])
def test_bad_usd_scene_is_one_line(tmp_path, content, words):
    path = tmp_path / "scene.usda"
    if content is not None:
        path.write_text(content)
    r = run_cli("info", str(path))
    assert r.returncode == 1
    assert "Traceback" not in r.stderr and words in r.stderr


def test_tetrahedralize_then_quality(tmp_path):
    out = tmp_path / "peanut_volume.usda"
    r = run_cli("tetrahedralize", "peanut", "--cellsize", "0.15", "--out", str(out))
    assert r.returncode == 0, r.stderr
    mesh = wb.usd.load_tetmesh(out)
    direct = wb.tetrahedralize(wb.scenes.peanut(), cellsize=0.15)
    assert mesh.tets.shape == direct.tets.shape
    r = run_cli("quality", str(out))
    assert r.returncode == 0, r.stderr
    q = direct.quality()
    assert f"{q.dihedral_min:.2f}" in r.stdout


@pytest.mark.parametrize(
    "args, words",
    [
        (("tetrahedralize", "tumor", "--cellsize", "0.1", "--interior-cellsize", "0.05", "--out", "v.usda"), "interior"),
        (("tetrahedralize", "tumor", "--cellsize", "0.1", "--out", "v.vtk"), "v.vtk"),
        (("quality", "missing.usda"), "missing.usda"),
    ],
)
def test_volume_errors_are_one_line(tmp_path, args, words):
    r = run_cli(*args, cwd=tmp_path)
    assert r.returncode == 1 and "Traceback" not in r.stderr and words in r.stderr
