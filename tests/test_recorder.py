"""Animated USD stages of cuts, simulations and tools, read back with pxr alone."""

import os

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdShade

import warpblob as wb
from warpblob.cut import SweepSurface, cut
from warpblob.mesh import TetMesh, TetStructure, box_tetmesh

from test_usd import validation_errors


def _edges_closed(faces: np.ndarray) -> bool:
    """Every edge of the triangles in exactly two faces, once in each direction (closed and oriented)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    fwd = {tuple(x) for x in e.tolist()}
    return len(fwd) == len(e) and all((b, a) in fwd for a, b in fwd)


def _visible_pieces(stage, base, code):
    """{piece path: (F, 3) faces in structure node ids} of the pieces visible at ``code`` (pxr only)."""
    out = {}
    for piece in stage.GetPrimAtPath(base + "/Pieces").GetChildren():
        if UsdGeom.Imageable(piece).ComputeVisibility(code) == UsdGeom.Tokens.invisible:
            continue
        faces = []
        for mesh in piece.GetChildren():
            if UsdGeom.Imageable(mesh).ComputeVisibility(code) == UsdGeom.Tokens.invisible:
                continue
            geom = UsdGeom.Mesh(mesh)
            node = np.asarray(UsdGeom.PrimvarsAPI(geom).GetPrimvar("warpblob:node").Get(code))
            f = np.asarray(geom.GetFaceVertexIndicesAttr().Get(code)).reshape(-1, 3)
            assert len(np.asarray(geom.GetPointsAttr().Get(code))) == len(node)
            faces.append(node[f])
        out[str(piece.GetPath())] = np.concatenate(faces)
    return out


def _two_material_box(n=4):
    box = box_tetmesh((0, 0, 0), (1, 1, 1), (n, n, n))
    inner = box.nodes[box.tets].mean(axis=1)[:, 2] > 0.5
    return TetMesh(box.nodes, box.tets, inner.astype(np.int32))


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_recorded_cuts_read_back_with_pxr(tmp_path, suffix):
    s = TetStructure.from_tetmesh(_two_material_box())
    blade = wb.tools.Scalpel(1.5, 0.1)
    path = wb.tools.Path.line((0.4, -0.5, -0.2), (0.4, 1.5, -0.2), 0.1, align=True)
    colors = {0: (0.9, 0.2, 0.1), 1: (0.1, 0.3, 0.9)}
    rec = wb.usd.Recorder(tmp_path / f"run{suffix}", fps=50, flush_bytes=4096)
    rec.add(s, name="Tissue", material_colors=colors)
    rec.add(blade, path)
    counts, pieces, changed = [], [], []
    planes = {2: ((0.41, 0.5, 0.5), (1, 0.1, 0.05)), 4: ((0.5, 0.53, 0.5), (0.05, 1, 0.1))}
    components = 1
    for frame in range(6):
        if frame in planes:
            result = cut(s, SweepSurface.plane(*planes[frame], 3.0))
            components = result.components
            changed.append(frame)
        counts.append(s.cell_count)
        pieces.append(components)
        rec.frame()
    out = rec.close()
    assert out.exists() and not list(tmp_path.glob(".*tmp*"))
    assert pieces == [1, 1, 2, 2, 4, 4]
    if suffix == ".usdc":
        assert rec.saves > 1  # streamed: saved while recording

    stage = Usd.Stage.Open(str(out))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 5
    assert stage.GetTimeCodesPerSecond() == 50 and stage.GetFramesPerSecond() == 50
    layer = stage.GetRootLayer()
    assert layer.HasTimeCodesPerSecond() and layer.HasFramesPerSecond()
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetName() == "World"
    tet = UsdGeom.TetMesh(stage.GetPrimAtPath("/World/Tissue/Volume"))
    material = UsdGeom.PrimvarsAPI(tet).GetPrimvar("materialId")
    assert material.GetInterpolation() == UsdGeom.Tokens.uniform
    # topology samples only where it changed (and at the first frame)
    expect = [0.0] + [float(f) for f in changed]
    assert tet.GetTetVertexIndicesAttr().GetTimeSamples() == expect
    assert tet.GetSurfaceFaceVertexIndicesAttr().GetTimeSamples() == expect
    assert material.GetAttr().GetTimeSamples() == expect
    assert len(tet.GetPointsAttr().GetTimeSamples()) == 6
    for piece in stage.GetPrimAtPath("/World/Tissue/Pieces").GetChildren():
        for mesh in piece.GetChildren():
            samples = UsdGeom.Mesh(mesh).GetFaceVertexIndicesAttr().GetTimeSamples()
            assert set(samples) <= set(expect)
    for frame in range(6):
        code = Usd.TimeCode(frame)
        tets = np.asarray(tet.GetTetVertexIndicesAttr().Get(code))
        points = np.asarray(tet.GetPointsAttr().Get(code))
        assert len(tets) == counts[frame] and np.isfinite(points).all()
        assert len(np.asarray(material.Get(code))) == counts[frame]
        assert len(UsdGeom.TetMesh.FindInvertedElements(tet, code)) == 0
        # one visible piece prim per separated piece, each closed; together they are the TetMesh's boundary
        visible = _visible_pieces(stage, "/World/Tissue", code)
        assert len(visible) == pieces[frame]
        assert all(_edges_closed(f) for f in visible.values())
        boundary = np.asarray(tet.GetSurfaceFaceVertexIndicesAttr().Get(code))
        union = np.concatenate(list(visible.values()))
        assert len(union) == len(boundary)
        assert {tuple(sorted(f)) for f in union.tolist()} == {tuple(sorted(f)) for f in boundary.tolist()}
        # the tool's pose at each time code is the path's
        xf = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Tool"))
        m = xf.ComputeLocalToWorldTransform(code)
        pose = path.pose(frame / 50)
        np.testing.assert_allclose(np.array(m.ExtractTranslation()), pose.position, atol=1e-9)
        local = np.array([0.3, 0.2, 0.1])
        np.testing.assert_allclose(np.array(m.Transform(Gf.Vec3d(*local))), pose.apply(local), atol=1e-9)
    # a piece made by a cut is invisible before it appears
    late = stage.GetPrimAtPath("/World/Tissue/Pieces/Piece3")
    assert [UsdGeom.Imageable(late).ComputeVisibility(f) for f in (0, 3, 4)] == ["invisible", "invisible", "inherited"]
    # one material per tissue, its colour the given one, bound to that tissue's meshes
    for mesh in stage.GetPrimAtPath("/World/Tissue/Pieces/Piece0").GetChildren():
        m = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("materialId").Get()
        bound, _ = UsdShade.MaterialBindingAPI(mesh).ComputeBoundMaterial()
        assert bound.GetPath() == f"/World/Looks/Material{m}"
        shader = UsdShade.Shader(stage.GetPrimAtPath(f"/World/Looks/Material{m}/PreviewSurface"))
        np.testing.assert_allclose(shader.GetInput("diffuseColor").Get(), colors[m], atol=1e-6)
    assert validation_errors(out) == []
    # the library's readers agree
    back = wb.usd.load_tetmesh(out, time=5)
    assert back.tet_count == counts[5] and np.isclose(back.volume(), 1.0, rtol=1e-5)
    assert set(np.unique(back.material).tolist()) == {0, 1}
    surf = wb.usd.load_mesh(out, time=3)
    assert surf.is_cut is not None and surf.is_cut.any() and surf.is_closed_manifold()
    assert surf.face_count == len(np.asarray(tet.GetSurfaceFaceVertexIndicesAttr().Get(3)))
    # the tool's recorded path reads back as a Path: its pose at each time code is the path's
    back_path = wb.tools.Path.from_usd(out, "/World/Tool")
    for t in np.arange(6) / 50:
        np.testing.assert_allclose(back_path.pose(t).position, path.pose(t).position, atol=1e-9)
        np.testing.assert_allclose(back_path.pose(t).apply([0.3, 0.2, 0.1]), path.pose(t).apply([0.3, 0.2, 0.1]),
                                   atol=1e-9)  # fmt: skip


def test_record_a_simulation_that_cuts_while_it_steps(tmp_path):
    beam = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (10, 2, 2))
    s = TetStructure.from_tetmesh(beam)
    sim = wb.Simulation(s, young=1e6, poisson=0.3, density=1000.0, fixed=beam.nodes[:, 0] == 0.0)
    blade = wb.tools.Scalpel(0.6, 0.05)
    path = wb.tools.Path.line((0.52, -0.3, -0.2), (0.52, 0.5, -0.2), 0.2, align=True)
    cutter = sim.add_tool(blade, path, cut=True)
    counts = []
    out = sim.record(tmp_path / "cut.usdc", 40, every=2, on_frame=lambda k: counts.append(s.cell_count))
    assert cutter.results[-1].components == 2
    stage = Usd.Stage.Open(str(out))
    assert stage.GetEndTimeCode() == 20 and stage.GetTimeCodesPerSecond() == pytest.approx(1 / (2 * sim.dt))
    tet = UsdGeom.TetMesh(stage.GetPrimAtPath("/Simulation/Volume"))
    samples = tet.GetTetVertexIndicesAttr().GetTimeSamples()
    assert len(samples) == 2 and samples[0] == 0.0  # the one cut, on release
    changed = [k for k in range(1, 21) if counts[k] != counts[k - 1]]
    assert samples[1:] == [float(k) for k in changed]
    for k in range(21):
        assert len(tet.GetTetVertexIndicesAttr().Get(k)) == counts[k]
        assert len(UsdGeom.TetMesh.FindInvertedElements(tet, Usd.TimeCode(k))) == 0
        assert len(_visible_pieces(stage, "/Simulation", Usd.TimeCode(k))) == (2 if k >= changed[0] else 1)
    # the cutter's Xform follows its path in simulation time
    xf = UsdGeom.Xformable(stage.GetPrimAtPath("/Simulation/Tools/Tool0"))
    for k in (0, 7, 20):
        t = k * 2 * sim.dt
        np.testing.assert_allclose(np.array(xf.ComputeLocalToWorldTransform(k).ExtractTranslation()),
                                   path.pose(t).position, atol=1e-9)  # fmt: skip
    z = [np.asarray(tet.GetPointsAttr().Get(k))[:, 2].min() for k in range(21)]
    assert z[-1] < z[changed[0]] - 0.05  # the severed end falls
    assert validation_errors(out) == []


def test_a_failed_recording_leaves_nothing(tmp_path):
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (2, 2, 2)))
    with pytest.raises(RuntimeError, match="boom"), wb.usd.Recorder(tmp_path / "x.usdc", flush_bytes=1) as rec:
        rec.add(s)
        rec.frame()
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _record_moving_box(path, frames, flush_bytes):
    """Record ``frames`` frames of a 50,400-tet box whose points move every frame; (max RSS growth MB, rest, wave)."""
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (21, 20, 20)))
    assert s.cell_count == 50400
    rest = np.asarray(s.node_rest).copy()
    wave = np.sin(np.pi * rest[:, 0]).astype(np.float32)
    rec = wb.usd.Recorder(path, fps=100, flush_bytes=flush_bytes)
    rec.add(s)
    rec.frame()
    start, growth = _rss_mb(), 0.0
    for k in range(1, frames):
        s.set_positions(rest + np.float32(0.01 * np.sin(k / 10.0)) * wave[:, None])
        rec.frame()
        if k % 50 == 0:
            growth = max(growth, _rss_mb() - start)
    rec.close()
    return growth, rest, wave


def _growth_in_a_fresh_process(path, frames: int, flush_bytes: int) -> float:
    """The RSS growth (MB) of :func:`_record_moving_box` run in a new Python process."""
    import subprocess
    import sys

    code = (f"import sys; sys.path.insert(0, {os.path.dirname(os.path.abspath(__file__))!r}); "
            f"from test_recorder import _record_moving_box; "
            f"print(_record_moving_box({str(path)!r}, {frames}, {flush_bytes})[0])")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    return float(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs /proc for RSS")
def test_a_long_recording_streams_to_disk_in_bounded_memory(tmp_path):
    # 1,000 frames of a 50,400-tet box, its points set directly each frame (a simulation per frame would take
    # minutes): ~147 MB of time samples. Streamed (saved every 8 MiB) the process grows by well under the bound;
    # the same recording held in memory (never saved until close) grows past it, so the measurement can tell.
    # Each recording runs in a fresh process: in this one, memory freed by earlier tests would serve the held
    # recording's growth without RSS rising, and the control could not tell.
    frames, bound_mb = 1000, 48.0
    growth = _growth_in_a_fresh_process(tmp_path / "long.usdc", frames, 8 << 20)
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (21, 20, 20)))
    rest = np.asarray(s.node_rest).copy()
    wave = np.sin(np.pi * rest[:, 0]).astype(np.float32)
    assert 12 * len(rest) * frames > 2 * bound_mb * 2**20  # the volume's points alone would not fit in the bound
    assert growth < bound_mb, f"RSS grew {growth:.1f} MB"
    held = _growth_in_a_fresh_process(tmp_path / "held.usdc", frames, 1 << 40)
    assert held > bound_mb, f"held in memory, RSS grew only {held:.1f} MB"
    stage = Usd.Stage.Open(str(tmp_path / "long.usdc"))
    points = UsdGeom.TetMesh(stage.GetPrimAtPath("/World/Volume/Volume")).GetPointsAttr()
    assert points.GetNumTimeSamples() == frames
    k = 777
    expect = rest + np.float32(0.01 * np.sin(k / 10.0)) * wave[:, None]
    np.testing.assert_allclose(np.asarray(points.Get(k)), expect, atol=1e-7)


def test_recorder_errors(tmp_path):
    with pytest.raises(wb.SceneError, match="path must end"):
        wb.usd.Recorder(tmp_path / "x.txt")
    with pytest.raises(wb.SceneError, match="does not exist"):
        wb.usd.Recorder(tmp_path / "missing" / "x.usdc")
    with pytest.raises(wb.SceneError, match="fps"):
        wb.usd.Recorder(tmp_path / "x.usda", fps=0)
    with pytest.raises(wb.SceneError, match="flush_bytes"):
        wb.usd.Recorder(tmp_path / "x.usdc", flush_bytes=0)
    rec = wb.usd.Recorder(tmp_path / "x.usda")
    with pytest.raises(wb.SceneError, match="cannot record"):
        rec.add(42)
    with pytest.raises(wb.SceneError, match="path"):
        rec.add(wb.tools.Probe(0.1))
    with pytest.raises(wb.SceneError, match="material_colors"):
        rec.add(TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (1, 1, 1))), material_colors={0: (1, 2)})
    rec.frame(0.5)
    with pytest.raises(wb.SceneError, match="not after"):
        rec.frame(0.25)
    rec.close()
    with pytest.raises(wb.SceneError, match="closed"):
        rec.frame()


def test_the_mesh_types_do_not_import_io():
    # one-way layout: warpblob.io reads and writes the mesh types, which never import it (not even lazily)
    import ast
    import pathlib

    import warpblob.mesh

    for source in pathlib.Path(warpblob.mesh.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(source.read_text())):
            if isinstance(node, ast.ImportFrom):
                module = "." * node.level + (node.module or "")
                assert not module.startswith(("..io", "warpblob.io", "..usd", "warpblob.usd")), (source.name, module)
            elif isinstance(node, ast.Import):
                assert not any(a.name.startswith(("warpblob.io", "warpblob.usd")) for a in node.names), source.name
