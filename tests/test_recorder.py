"""Animated USD stages of cuts and tools, read back with pxr alone."""

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom

import warpblob as wb
from warpblob.cut import SweepSurface, cut
from warpblob.mesh import TetStructure, box_tetmesh

from test_usd import validation_errors


def _edges_closed(faces: np.ndarray) -> bool:
    """Every edge of the triangles in exactly two faces, once in each direction (closed and oriented)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    fwd = {tuple(x) for x in e.tolist()}
    return len(fwd) == len(e) and all((b, a) in fwd for a, b in fwd)


@pytest.mark.parametrize("suffix", [".usda", ".usdc"])
def test_recorded_cuts_read_back_with_pxr(tmp_path, suffix):
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (4, 4, 4)))
    blade = wb.tools.Scalpel(1.5, 0.1)
    path = wb.tools.Path.line((0.4, -0.5, -0.2), (0.4, 1.5, -0.2), 0.1, align=True)
    rec = wb.usd.Recorder(tmp_path / f"run{suffix}", fps=50)
    rec.add(s, name="Tissue", model=wb.scenes.tumor())
    rec.add(blade, path)
    counts, changed = [], []
    planes = {2: ((0.41, 0.5, 0.5), (1, 0.1, 0.05)), 4: ((0.5, 0.53, 0.5), (0.05, 1, 0.1))}
    for frame in range(6):
        if frame in planes:
            cut(s, SweepSurface.plane(*planes[frame], 3.0))
            changed.append(frame)
        counts.append(s.cell_count)
        rec.frame()
    out = rec.close()
    assert out.exists() and not list(tmp_path.glob("*.tmp*"))

    stage = Usd.Stage.Open(str(out))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 5
    assert stage.GetTimeCodesPerSecond() == 50 and stage.GetFramesPerSecond() == 50
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z and stage.GetDefaultPrim().GetName() == "World"
    tet = UsdGeom.TetMesh(stage.GetPrimAtPath("/World/Tissue/Volume"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Tissue/Surface"))
    # topology samples only where it changed (and at the first frame)
    assert tet.GetTetVertexIndicesAttr().GetTimeSamples() == [0.0] + [float(f) for f in changed]
    assert mesh.GetFaceVertexIndicesAttr().GetTimeSamples() == [0.0] + [float(f) for f in changed]
    assert len(tet.GetPointsAttr().GetTimeSamples()) == 6
    for frame in range(6):
        code = Usd.TimeCode(frame)
        tets = np.asarray(tet.GetTetVertexIndicesAttr().Get(code))
        points = np.asarray(tet.GetPointsAttr().Get(code))
        assert len(tets) == counts[frame] and np.isfinite(points).all()
        assert len(UsdGeom.TetMesh.FindInvertedElements(tet, code)) == 0
        faces = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(code)).reshape(-1, 3)
        assert _edges_closed(faces)
        cut_faces = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("isCut").Get(code))
        assert len(cut_faces) == len(faces) and (cut_faces.any() == (frame >= 2))
        # the tool's pose at each time code is the path's
        xf = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Tool"))
        m = xf.ComputeLocalToWorldTransform(code)
        pose = path.pose(frame / 50)
        np.testing.assert_allclose(np.array(m.ExtractTranslation()), pose.position, atol=1e-6)
        local = np.array([0.3, 0.2, 0.1])
        world = np.array(m.Transform(Gf.Vec3d(*local)))
        np.testing.assert_allclose(world, pose.apply(local), atol=1e-5)
    assert validation_errors(out) == []
    # the library's readers agree
    back = wb.usd.load_tetmesh(out, time=5)
    assert back.tet_count == counts[5] and np.isclose(back.volume(), 1.0, rtol=1e-5)
    surf = wb.usd.load_mesh(out, time=3)
    assert surf.is_cut is not None and surf.is_cut.any() and surf.is_closed_manifold()


def test_recorder_records_a_simulation_with_cuts(tmp_path):
    beam = box_tetmesh((0, 0, 0), (1.0, 0.2, 0.2), (8, 2, 2))
    s = TetStructure.from_tetmesh(beam)
    sim = wb.Simulation(s, young=1e6, poisson=0.3, density=1000.0, fixed=beam.nodes[:, 0] == 0.0)
    with wb.usd.Recorder(tmp_path / "sim.usdc") as rec:
        rec.add(sim)
        for frame in range(8):
            if frame == 3:
                s.set_positions(sim.positions)
                r = cut(s, SweepSurface.plane((0.61, 0.1, 0.1), (1, 0, 0.1), 2.0), collect=False)
                from warpblob.cut._sim import apply_cut

                apply_cut(sim, r)
            sim.step()
            rec.frame()
    stage = Usd.Stage.Open(str(tmp_path / "sim.usdc"))
    tet = UsdGeom.TetMesh(stage.GetPrimAtPath("/World/Simulation/Volume"))
    assert tet.GetTetVertexIndicesAttr().GetTimeSamples() == [0.0, 3.0]
    z = [np.asarray(tet.GetPointsAttr().Get(Usd.TimeCode(f)))[:, 2].min() for f in range(8)]
    assert z[-1] < z[3] - 0.05  # the severed end falls


def test_recorder_errors(tmp_path):
    with pytest.raises(wb.SceneError, match="path must end"):
        wb.usd.Recorder(tmp_path / "x.txt")
    with pytest.raises(wb.SceneError, match="fps"):
        wb.usd.Recorder(tmp_path / "x.usda", fps=0)
    rec = wb.usd.Recorder(tmp_path / "x.usda")
    with pytest.raises(wb.SceneError, match="cannot record"):
        rec.add(42)
    with pytest.raises(wb.SceneError, match="path"):
        rec.add(wb.tools.Probe(0.1))
    rec.frame(0.5)
    with pytest.raises(wb.SceneError, match="not after"):
        rec.frame(0.25)
