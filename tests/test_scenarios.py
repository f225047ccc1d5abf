"""The thesis' tool-contact scenarios: the tumor keeps its volume under the probe (nu = 0.45, two cell sizes),
with no inverted tet and a finite energy; the green slab fixed to the wall does not move while the others
are pushed; the cake does not sink through the ground; ``warpblob scenario`` writes its stage and pictures.
"""

import argparse

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from warpblob import WarpblobError
from warpblob.scenarios import press_cake, probe_tumor, push_three_slabs
from warpblob.scenarios._command import add_scenario_parser, run_scenario

STEPS = 90


def tet_volumes(sim) -> np.ndarray:
    x = sim.positions.astype(np.float64)
    t = sim.elements.tets_host
    a, b, c, d = (x[t[:, k]] for k in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


@pytest.mark.parametrize("cellsize", [0.35, 0.25])
def test_the_probed_tumor_keeps_its_volume_within_one_percent(cellsize):
    sim = probe_tumor(cellsize, STEPS)
    rest = sim.volume()
    pressed = 0.0
    for _ in range(STEPS):
        sim.step()
        pressed = max(pressed, float(sim.contact_force(0)[2]))
        assert abs(sim.volume() - rest) / rest < 0.01
    assert pressed > 0 and sim.stats["contact"]["penetrating"] > 0
    moved = sim.rest_positions[:, 2].max() - sim.positions[:, 2].max()
    assert moved > 0.05  # the top went down under the probe
    assert tet_volumes(sim).min() > 0
    assert np.isfinite(sim.energy()["total"])
    assert sim.volume() < rest  # compressed, a little


def test_the_green_slab_stays_on_the_wall_while_the_others_are_pushed():
    sim = push_three_slabs(0.3, STEPS)
    wall = sim.positions[sim.fixed]
    free = np.setdiff1d(np.arange(sim.node_count), sim.fixed)
    start = sim.positions[free]
    sim.step(STEPS)
    assert np.array_equal(sim.positions[sim.fixed], wall)
    assert sim.contact_force(0)[0] > 0  # the slabs push the probe back along +x
    assert (start[:, 0] - sim.positions[free, 0]).max() > 0.2  # the blue slab's end went in
    assert tet_volumes(sim).min() > 0


def test_the_cake_does_not_sink_through_the_ground():
    sim = press_cake(0.5, STEPS)
    floor = sim.ground[0]
    lowest = np.inf
    for _ in range(STEPS):
        sim.step()
        lowest = min(lowest, float(sim.positions[:, 2].min()))
    assert lowest >= floor - 1e-6
    assert sim.contact_force(0)[2] > 0
    assert sim.rest_positions[:, 2].max() - sim.positions[:, 2].max() > 0.2  # pressed from above
    assert tet_volumes(sim).min() > 0


def test_scenario_errors_name_the_value():
    with pytest.raises(WarpblobError, match="-1"):
        probe_tumor(-1.0, 10)
    with pytest.raises(WarpblobError, match="steps.*1"):
        press_cake(0.5, 1)


def test_the_scenario_command_writes_a_stage_and_pictures(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    add_scenario_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["scenario", "probe_tumor", "--out", str(tmp_path / "run"), "--cellsize", "0.5",
                              "--steps", "12", "--every", "2", "--frames", "2"])  # fmt: skip
    args.device = None
    assert run_scenario(args) == 0
    assert "volume change" in capsys.readouterr().out
    stage = Usd.Stage.Open(str(tmp_path / "run" / "probe_tumor.usda"))
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 6
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    tool = UsdGeom.Xformable(stage.GetPrimAtPath("/Simulation/Tools/Tool0"))
    translate = tool.GetOrderedXformOps()[0].GetAttr()
    assert len(translate.GetTimeSamples()) == 7
    assert translate.Get(6)[2] < translate.Get(0)[2]  # the probe came down
    assert UsdGeom.Mesh(stage.GetPrimAtPath("/Simulation/Tools/Tool0/Mesh")).GetPointsAttr().Get() is not None
    colors = UsdGeom.Mesh(stage.GetPrimAtPath("/Simulation/Surface")).GetDisplayColorPrimvar()
    assert len(colors.GetAttr().GetTimeSamples()) == 7
    pictures = sorted((tmp_path / "run").glob("probe_tumor_*.png"))
    assert [p.name for p in pictures] == ["probe_tumor_0000.png", "probe_tumor_0006.png"]
    assert pictures[-1].read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(WarpblobError, match="--steps"):
        run_scenario(parser.parse_args(["scenario", "press_cake", "--out", str(tmp_path), "--steps", "1"]))
