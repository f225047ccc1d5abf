"""Drilling: a trephine bores plugs out of the eggshell; the plug is one closed piece of the right volume."""

import numpy as np
import pytest

import warpblob as wb
from warpblob.cut import SweepSurface, cut
from warpblob.mesh import TetStructure
from warpblob.scenarios import drill_eggshell, drill_steps, total_steps
from warpblob.scenarios._drilling import DRILL_RADIUS, EGGSHELL_RADII, _holes

SNAP = 0.2
CELL = 0.14  # the coarsest size at which the 0.18 shell is not pinched


@pytest.fixture(scope="module")
def shell():
    return wb.tetrahedralize(wb.scenes.eggshell(), cellsize=CELL)


def _bore(x, y, stop=None, *, segments=16, start=None):
    """A drill rising along z through the bottom of the shell at (x, y) (the scenario's stroke), to ``stop``."""
    outer, inner = EGGSHELL_RADII
    near, far = max(np.hypot(x, y) - DRILL_RADIUS, 0.0), np.hypot(x, y) + DRILL_RADIUS
    z0 = -np.sqrt(outer**2 - near**2) - 0.08 if start is None else start
    z1 = -np.sqrt(inner**2 - far**2) + 0.1 if stop is None else stop
    drill = wb.tools.Drill(DRILL_RADIUS, 0.6, segments=segments)
    path = wb.tools.Path.line((x, y, z0), (x, y, z1), 1.0, align=True)
    return SweepSurface.from_path(drill, path, dt=0.05), drill


def _prism_volume(mesh: wb.TetMesh, x, y, segments=16) -> float:
    """Volume of ``mesh`` inside the drill's wall prism under z = 0 (VTK's exact clip by each plane): the reference."""
    grid = mesh.to_pyvista().clip(normal=[0.0, 0.0, 1.0], origin=[0.0, 0.0, 0.0], crinkle=False)  # keeps z < 0
    angle = 2 * np.pi * (np.arange(segments) + 0.5) / segments
    apothem = DRILL_RADIUS * np.cos(np.pi / segments)
    for a in angle:
        n = np.array([np.cos(a), np.sin(a), 0.0])
        grid = grid.clip(normal=list(n), origin=[x + apothem * n[0], y + apothem * n[1], 0.0], crinkle=False)
    return float(grid.compute_cell_sizes().cell_data["Volume"].sum())


def _edge(mesh):
    p = mesh.nodes[mesh.tets].astype(np.float64)
    return max(float(np.linalg.norm(p[:, i] - p[:, j], axis=1).max()) for i in range(4) for j in range(i))


def _pieces(s):
    labels = s.components()[np.asarray(s.cell_alive)]
    return labels, np.bincount(labels)


def test_eggshell_drilled_once_frees_one_closed_plug_of_the_prism_volume(shell, device):
    s = TetStructure.from_tetmesh(shell)
    sweep, drill = _bore(0.013, -0.009)
    r = cut(s, sweep, snap=SNAP, device=device)
    assert r.components == 2
    s.check()
    tm, rest = s.to_tetmesh(), s.to_tetmesh(rest=True)
    assert tm.volumes().min() > 0 and rest.volumes().min() > 0
    assert abs(rest.volume() - shell.volume()) <= 1e-6 * shell.volume()
    labels, sizes = _pieces(s)
    plug = int(np.argmin(sizes))
    volume = float(tm.volumes()[labels == plug].sum())
    reference = _prism_volume(shell, 0.013, -0.009)
    # the wall area inside the shell: the prism's side times the shell's thickness along z (about 0.19 here)
    wall = 16 * 2 * DRILL_RADIUS * np.sin(np.pi / 16) * 0.2
    assert abs(volume - reference) <= wall * SNAP * _edge(shell), (volume, reference)
    surf = s.surface()
    assert surf.is_closed_manifold() and surf.shell_count() == 2  # the hole joins the shell's two sides; the plug
    for p in range(2):  # each piece alone is closed
        piece = wb.TetMesh(tm.nodes, tm.tets[labels == p])
        assert TetStructure.from_tetmesh(piece).surface().is_closed_manifold()


def test_six_holes_make_six_plugs(shell):
    s = TetStructure.from_tetmesh(shell)
    for x, y in _holes(6):
        cut(s, _bore(x, y)[0], snap=SNAP)
    labels, sizes = _pieces(s)
    assert len(sizes) == 7
    assert abs(s.to_tetmesh(rest=True).volume() - shell.volume()) <= 1e-6 * shell.volume()
    assert s.to_tetmesh().volumes().min() > 0


def test_a_drill_stopped_in_the_wall_leaves_a_groove_and_going_on_frees_the_plug(shell):
    s = TetStructure.from_tetmesh(shell)
    outer, inner = EGGSHELL_RADII
    middle = -0.5 * (outer + inner)  # the bit halfway through the wall at the axis
    first = cut(s, _bore(0.013, -0.009, stop=middle)[0], snap=SNAP)
    assert first.components == 1 and first.tets_added > 0
    s.check()
    groove = s.surface()
    assert groove.is_closed_manifold() and groove.is_cut.any()  # a closed groove, open to the outside only
    cut_depth = groove.vertices[groove.faces[groove.is_cut]][..., 2]
    assert cut_depth.max() < middle + 0.2 * CELL  # the groove stops about where the bit did
    second = cut(s, _bore(0.013, -0.009, start=middle - 0.02)[0], snap=SNAP)
    assert second.components == 2
    s.check()
    assert s.to_tetmesh().volumes().min() > 0
    assert s.surface().is_closed_manifold()


def test_drill_eggshell_scenario_drops_the_plug():
    sim = drill_eggshell(CELL)
    top = float(sim.positions[:, 2].min())
    steps = total_steps(sim)
    sim.step(steps)
    assert sim.stats["components"] == 2
    s = sim._structure
    labels, sizes = _pieces(s)
    plug = int(np.argmin(sizes))
    live = np.asarray(s.cell_nodes)[np.asarray(s.cell_alive)]
    plug_nodes = np.unique(live[labels == plug])
    x = sim.positions
    # the plug left its hole: its highest point is now below where the shell's lowest point was
    assert x[plug_nodes, 2].max() < top
    assert x[plug_nodes, 2].min() >= sim.ground[0] - 1e-3
    rows = drill_steps(sim)
    assert rows and rows[-1]["components"] == 2
    assert sum(r["tets_cut"] for r in rows) > 0
    assert all(set(r["ms"]) >= {"intersection", "classification", "subdivision", "topology", "total"} for r in rows)


@pytest.mark.parametrize("holes", [0, 13, 2.0, True])
def test_bad_hole_counts_are_refused(holes):
    with pytest.raises(wb.WarpblobError, match="holes"):
        drill_eggshell(CELL, holes=holes)


def test_the_scenario_command_records_the_cuts(tmp_path, capsys):
    """``warpblob scenario cut_tumor``: the stage's last frame has the tets and pieces the run ended with."""
    import argparse
    import json

    from pxr import Usd, UsdGeom

    from warpblob.scenarios._command import add_scenario_parser, run_scenario

    parser = argparse.ArgumentParser()
    add_scenario_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "run"
    args = parser.parse_args(["scenario", "cut_tumor", "--out", str(out), "--cellsize", "0.25", "--frames", "2",
                              "--every", "6", "--usdc"])  # fmt: skip
    assert run_scenario(args) == 0
    report = capsys.readouterr().out
    rows = json.loads((out / "cut_tumor_steps.json").read_text())["steps"]
    pieces_expected = _pieces_of_strokes(0.25)
    assert len(rows) == 3 and rows[-1]["components"] == pieces_expected >= 4
    stage = Usd.Stage.Open(str(out / "cut_tumor.usdc"))
    end = stage.GetEndTimeCode()
    tets = UsdGeom.TetMesh(stage.GetPrimAtPath("/Simulation/Volume"))
    counts = [len(tets.GetTetVertexIndicesAttr().Get(t)) for t in (0, end)]
    assert counts[0] < counts[1]
    pieces = [p for p in stage.GetPrimAtPath("/Simulation/Pieces").GetChildren()]
    visible = [p for p in pieces if UsdGeom.Imageable(p).ComputeVisibility(end) != UsdGeom.Tokens.invisible]
    assert len(visible) == pieces_expected
    first_blade = UsdGeom.Imageable(stage.GetPrimAtPath("/Simulation/Tools/Tool0"))  # its stroke is over at the end
    assert [first_blade.ComputeVisibility(t) for t in (0, end)] == ["inherited", "invisible"]
    assert len(list(out.glob("cut_tumor_*.png"))) == 2 and f"{pieces_expected} pieces" in report


def _pieces_of_strokes(cellsize):
    """The reference: the tumor's tets grouped by the sides of the three stroke planes (each stroke sweeps
    the vertical plane through its path), the connected groups counted (independent of the cutter)."""
    from warpblob.scenarios import cut_tumor

    sim = cut_tumor(cellsize)
    mesh = sim._structure.to_tetmesh(rest=True)
    centroid = mesh.nodes[mesh.tets].mean(axis=1)
    side = np.zeros(mesh.tet_count, dtype=np.int64)
    for k, cutter in enumerate(sim.cutters):
        start, end = cutter.path.positions[0], cutter.path.positions[-1]
        across = int(np.argmin(np.abs(end - start)[:2]))  # the horizontal axis the stroke does not move along
        side += (centroid[:, across] > start[across]).astype(np.int64) << k
    count = 0
    for region in np.unique(side):
        part = wb.TetMesh(mesh.nodes, mesh.tets[side == region])
        count += len(np.unique(TetStructure.from_tetmesh(part).components()))
    return count


def test_craniotomy_drills_bone_only_and_the_skull_stays_rigid():
    """Two holes in the rigid skull: only skull tets split; every other tet and its nodes as they were; the
    anchored skull does not move by a bit; each plug is a free rigid body (its nodes keep their distances)."""
    from warpblob.scenarios import craniotomy

    sim = craniotomy(0.3, cross_section=False)
    s = sim._structure
    before = s.to_tetmesh(rest=True)
    cells0 = np.asarray(s.cell_nodes).copy()
    soft = np.flatnonzero(before.material != 0)
    soft_nodes = np.unique(before.tets[soft])
    rest0 = np.asarray(s.node_rest).copy()
    x0 = sim.positions
    anchored = sim.anchors
    sim.step(total_steps(sim))
    results = [r for c in sim.cutters for r in c.results]
    removed = np.unique(np.concatenate([r.removed for r in results]))
    assert removed.size and np.all(np.asarray(s.cell_material)[removed] == 0)  # only bone was split
    alive = np.asarray(s.cell_alive)
    assert np.all(alive[soft]) and np.array_equal(np.asarray(s.cell_nodes)[soft], cells0[soft])
    assert np.array_equal(np.asarray(s.node_rest)[soft_nodes], rest0[soft_nodes])
    assert np.array_equal(sim.positions[anchored], x0[anchored])  # the anchored skull, bit for bit
    bodies = sim.rigid_bodies
    assert len(bodies["nodes"]) == 2  # the two plugs
    x, rest = sim.positions.astype(np.float64), np.asarray(s.node_rest, dtype=np.float64)
    for nodes in bodies["nodes"]:
        d = np.linalg.norm(x[nodes][:, None] - x[nodes][None], axis=2)
        d0 = np.linalg.norm(rest[nodes][:, None] - rest[nodes][None], axis=2)
        assert np.abs(d - d0).max() < 1e-4 * max(d0.max(), 1.0)
    tm = s.to_tetmesh()
    assert tm.volumes().min() > 0
    assert abs(s.to_tetmesh(rest=True).volume() - before.volume()) <= 1e-6 * before.volume()
    assert sum(r.split_cells for r in results) > 0


def test_a_progressive_drill_in_a_simulation_frees_the_plug_of_one_stroke():
    """The drill cuts every step (the stroke so far, its earlier cut nodes kept cut): when the bit has gone
    through, the plug is one closed piece of the prism's volume, as one whole stroke cuts it, and it falls."""
    from warpblob.mesh import box_tetmesh

    mesh = box_tetmesh((0, 0, 0), (1, 1, 0.3), (12, 12, 4))
    rim = (np.abs(mesh.nodes[:, 0] - 0.5) > 0.45) | (np.abs(mesh.nodes[:, 1] - 0.5) > 0.45)
    sim = wb.Simulation(TetStructure.from_tetmesh(mesh), young=1e6, poisson=0.3, density=1000.0, rigid={0},
                        anchors=rim)  # fmt: skip
    drill = wb.tools.Drill(0.2, 0.6, segments=16)
    path = wb.tools.Path.line((0.51, 0.49, 0.4), (0.51, 0.49, -0.1), 20 * sim.dt, align=True)
    cutter = sim.add_tool(drill, path, cut=True, mode="progressive")
    sim.step(24)
    assert len(cutter.results) >= 15 and sim.stats["components"] == 2  # a cut a step (from the first two samples)
    s = sim._structure
    labels, sizes = _pieces(s)
    plug = int(np.argmin(sizes))
    rest = s.to_tetmesh(rest=True)
    volume = float(rest.volumes()[labels == plug].sum())
    prism = 16 / 2 * 0.2**2 * np.sin(2 * np.pi / 16) * 0.3
    wall = 16 * 2 * 0.2 * np.sin(np.pi / 16) * 0.3
    assert abs(volume - prism) <= wall * SNAP * _edge(mesh)
    assert s.surface().is_closed_manifold() and rest.volumes().min() > 0
    live = np.asarray(s.cell_nodes)[np.asarray(s.cell_alive)]
    assert sim.positions[np.unique(live[labels == plug]), 2].max() < 0.3  # it fell out of its hole


def test_the_drill_scenario_runs_from_the_command_line(tmp_path, capsys):
    import argparse
    import json

    from warpblob.scenarios._command import add_scenario_parser, run_scenario

    parser = argparse.ArgumentParser()
    add_scenario_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "egg"
    args = parser.parse_args(["scenario", "drill_eggshell", "--out", str(out), "--cellsize", str(CELL),
                              "--frames", "1", "--every", "15"])  # fmt: skip
    assert run_scenario(args) == 0
    rows = json.loads((out / "drill_eggshell_steps.json").read_text())["steps"]
    assert len(rows) > 10 and rows[-1]["components"] == 2  # a cut per drill step; the plug came free
    assert (out / "drill_eggshell.usda").exists() and "2 pieces" in capsys.readouterr().out
