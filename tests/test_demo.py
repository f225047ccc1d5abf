"""``warpblob demo`` tells the truth: shells, volumes against Monte Carlo, the head cut open and resolved.

The references are independent of the demo: PyVista's connectivity filter
for the shells, the analytic volume of a sphere, and repeated Monte Carlo
runs for the standard error.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

import warpblob as wb
from warpblob.cli import _DEMO_CELLSIZE
from warpblob.field import monte_carlo_volume


def run_cli(*args, cwd=None):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run(
        [sys.executable, "-m", "warpblob.cli", *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=600
    )


def test_demo_head_shells_match_pyvista(tmp_path):
    """A coarse cell size (0.1) splits the head into many spurious shells: the count must still be exact."""
    import pyvista as pv
    from pxr import Usd, UsdGeom

    r = run_cli("demo", "--out", str(tmp_path), "--scene", "head", "--cellsize", "0.1", "--resolution", "16",
                "--samples", "20000")  # fmt: skip
    assert r.returncode == 0, r.stderr
    summary = json.loads((tmp_path / "summary.json").read_text())["head"]
    assert summary["model"] == "head (cut away)"
    poly = summary["polygonize"]
    stage = Usd.Stage.Open(str(tmp_path / "warpblob_demo.usdc"))
    geom = UsdGeom.Mesh(stage.GetPrimAtPath("/Demo/head/surface"))
    points = np.asarray(geom.GetPointsAttr().Get(), dtype=np.float64)
    faces = np.asarray(geom.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    assert len(faces) == poly["triangles"]
    cells = np.column_stack([np.full(len(faces), 3), faces]).ravel()
    regions = pv.PolyData(points, cells).connectivity(extraction_mode="all")
    count = len(np.unique(regions.cell_data["RegionId"]))
    assert poly["shells"] == count > 4
    assert poly["closed_manifold"] is True  # so sharing a vertex (PyVista) and an edge (warpblob) agree
    row = next(line for line in (tmp_path / "summary.txt").read_text().splitlines() if line.startswith("head"))
    assert f" {count} " in row


def test_monte_carlo_volume_of_a_sphere_and_its_error_bar():
    ball = wb.Point((0.0, 0.0, 0.0), 1.0)
    exact = 4.0 / 3.0 * np.pi * wb.ISO_DISTANCE**3
    mc = monte_carlo_volume(ball, samples=400_000, rng=1)
    assert mc.samples == 400_000
    assert abs(mc.volume - exact) < 3 * mc.standard_error
    mesh = wb.polygonize(ball, cellsize=0.03)
    assert abs(mesh.volume() - mc.volume) < 3 * mc.standard_error
    # the error bar is the spread of the estimate: 40 runs of 20,000 points
    runs = [monte_carlo_volume(ball, samples=20_000, rng=s) for s in range(40)]
    spread = np.std([m.volume for m in runs], ddof=1)
    assert 0.7 < spread / np.mean([m.standard_error for m in runs]) < 1.4


def test_demo_cell_size_resolves_the_head_layers():
    """At the demo's cell size the cut-away head is one shell per tissue, its volume that of the model,
    and the cut faces show the tissues' colours."""
    model = wb.scenes.head(cut_away=True)
    mesh = wb.polygonize(model, cellsize=_DEMO_CELLSIZE["head"])
    assert mesh.is_closed_manifold()
    assert mesh.shell_count() == len(wb.scenes.HEAD_TISSUES)
    mc = monte_carlo_volume(model, samples=1_000_000, rng=2)
    assert abs(mesh.volume() - mc.volume) < 3 * mc.standard_error
    # vertices on the cut planes (away from the rounded cut edges) carry exactly the four tissue colours
    v = mesh.vertices
    on_cut = (np.abs(v[:, 0]) < 1e-3) & (v[:, 1] < -0.2) & (v[:, 2] > 0.2)
    colours = np.unique(np.round(mesh.colors[on_cut], 3), axis=0)
    expected = np.unique(np.round(np.array(list(wb.scenes.HEAD_TISSUES.values())), 3), axis=0)
    np.testing.assert_allclose(colours, expected, atol=2e-3)


@pytest.mark.parametrize("samples", ["1", "-5"])
def test_demo_refuses_too_few_samples(tmp_path, samples):
    r = run_cli("demo", "--out", str(tmp_path / "out"), "--samples", samples)
    assert r.returncode == 2 and "--samples" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


def test_quick_demo_runs_the_whole_pipeline_into_one_animated_stage(tmp_path):
    """``warpblob demo --quick``: every stage's files, and the composed stage checked with pxr alone at every
    time code of each recorded scenario (tet counts against its own stage, topology sampled only where it
    changed, finite points, nothing inverted, the piece surfaces closed, no validator error)."""
    from pxr import Usd, UsdGeom

    from test_recorder import _edges_closed, _visible_pieces
    from test_usd import validation_errors

    r = run_cli("demo", "--out", str(tmp_path), "--quick")
    assert r.returncode == 0, r.stderr[-3000:]
    # the scenario references resolve while the stage is composed (no USD warnings), and nothing is left over
    assert "Could not open asset" not in r.stderr, r.stderr[-3000:]
    assert not list(tmp_path.glob(".*")), list(tmp_path.glob(".*"))
    summary = json.loads((tmp_path / "summary.json").read_text())
    pipeline = summary["pipeline"]
    for name in ("probe_tumor", "cut_tumor", "drill_eggshell"):
        assert (tmp_path / f"{name}.gif").read_bytes()[:3] == b"GIF"
        assert (tmp_path / f"{name}.usdc").exists()
    assert pipeline["cut_tumor"]["pieces"] >= 4 and pipeline["drill_eggshell"]["pieces"] == 2
    assert set(pipeline["tetrahedralize"]) == {"tumor", "eggshell", "head"}
    assert len(pipeline["tetrahedralize"]["head"]["tets_per_material"]) >= 4  # the head's tissues share one mesh
    assert all((tmp_path / f).exists() for f in ("tet_quality.png", "slice_mug.png", "summary.txt"))
    assert pipeline["slice"]["closed"] == [True, True]
    stage = Usd.Stage.Open(str(tmp_path / "warpblob_demo.usdc"))
    assert stage.GetDefaultPrim().GetName() == "Demo" and stage.GetEndTimeCode() > 0
    assert stage.GetRootLayer().HasTimeCodesPerSecond() and stage.GetRootLayer().HasFramesPerSecond()
    assert not stage.GetRootLayer().GetCompositionAssetDependencies()  # flattened: self-contained
    assert UsdGeom.Mesh(stage.GetPrimAtPath("/Demo/tumor/surface"))
    for name in ("cut_tumor", "drill_eggshell"):
        own = Usd.Stage.Open(str(tmp_path / f"{name}.usdc"))
        base = f"/Demo/Scenarios/{name}"
        tet = UsdGeom.TetMesh(stage.GetPrimAtPath(base + "/Volume"))
        mine = UsdGeom.TetMesh(own.GetPrimAtPath(own.GetDefaultPrim().GetPath().AppendPath("Volume")))
        samples = tet.GetTetVertexIndicesAttr().GetTimeSamples()
        points = tet.GetPointsAttr().GetTimeSamples()
        assert len(samples) > 1 and len(samples) < len(points)  # topology only where a cut changed it
        for code in points:
            tets = np.asarray(tet.GetTetVertexIndicesAttr().Get(code))
            assert len(tets) == len(np.asarray(mine.GetTetVertexIndicesAttr().Get(code)))
            assert np.isfinite(np.asarray(tet.GetPointsAttr().Get(code))).all()
            assert len(UsdGeom.TetMesh.FindInvertedElements(tet, Usd.TimeCode(code))) == 0
            assert all(_edges_closed(f) for f in _visible_pieces(stage, base, Usd.TimeCode(code)).values())
    assert validation_errors(tmp_path / "warpblob_demo.usdc") == []


def test_summary_explains_a_volume_outside_three_standard_errors():
    """A model whose mesh volume misses the Monte Carlo estimate by more than 3 s.e. gets a line saying why."""
    from warpblob.cli import _summary_lines

    def row(volume, estimate, error):
        return {"primitives": 1, "operators": 0, "depth": 1, "points_per_second": 1e6,
                "polygonize": {"cellsize": 0.1, "seconds": 0.1, "triangles": 10, "shells": 1,
                               "closed_manifold": True, "volume": volume},
                "volume_monte_carlo": {"volume": estimate, "standard_error": error}}  # fmt: skip

    lines = _summary_lines({"fine": row(1.0, 1.01, 0.01), "thin": row(1.1, 1.0, 0.01)}, 1000)
    notes = [line for line in lines if "volume is" in line]
    assert len(notes) == 1 and notes[0].startswith("thin:") and "+10.0%" in notes[0] and "0.1" in notes[0]
