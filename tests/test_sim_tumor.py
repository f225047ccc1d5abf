"""The thesis' volume check on the tumor model, and the ``simulate`` command with its time-sampled USD output.

A probe presses the top of the tumor (its four layers, three materials, nu = 0.45) down by 5% of its height
while the bottom is held; near-incompressible tissue keeps its volume within 1% at every cell size, where a
compressible one (nu = 0.3) loses clearly more.
"""

import argparse

import numpy as np
import pytest
from pxr import Usd, UsdGeom

import warpblob as wb
from warpblob.sim._command import add_simulate_parser, run_simulate

LAYERS = {0: 3e4, 1: 1e4, 2: 6e4}  # Young's moduli of the tumor's materials, Pa


def compressed_volume_change(cellsize: float, poisson: float) -> float:
    volume = wb.tetrahedralize(wb.scenes.tumor(), cellsize=cellsize)
    z = volume.nodes[:, 2]
    low, high = z.min(), z.max()
    height = high - low
    bottom = z < low + 0.1 * height
    probe = (z > high - 0.15 * height) & (np.linalg.norm(volume.nodes[:, :2], axis=1) < 0.6)
    sim = wb.Simulation(volume, young=LAYERS, poisson=poisson, density=1000.0, gravity=(0, 0, 0), fixed=bottom | probe)
    rest = sim.volume()
    targets = sim.fixed_positions
    targets[probe[sim.fixed], 2] -= 0.05 * height
    sim.fixed_positions = targets
    sim.solve_static()
    np.testing.assert_allclose(sim.positions[probe, 2], volume.nodes[probe, 2] - 0.05 * height, atol=1e-6)
    return (sim.volume() - rest) / rest


@pytest.mark.parametrize("cellsize", [0.4, 0.3, 0.25])
def test_a_compressed_tumor_keeps_its_volume_within_one_percent(cellsize):
    change = compressed_volume_change(cellsize, 0.45)
    assert abs(change) < 0.01
    assert change < 0  # it is compressed, a little


def test_a_compressible_tumor_loses_more_volume():
    assert abs(compressed_volume_change(0.4, 0.3)) > 2 * abs(compressed_volume_change(0.4, 0.45))


def test_simulate_command_writes_a_time_sampled_stage(tmp_path, capsys):
    parser = argparse.ArgumentParser()
    add_simulate_parser(parser.add_subparsers(dest="command"))
    out = tmp_path / "sim.usda"
    args = parser.parse_args(
        ["simulate", "tumor", "--cellsize", "0.5", "--steps", "6", "--out", str(out), "--fix-below", "-1.0"]
    )
    args.device = None
    assert run_simulate(args) == 0
    assert "wrote" in capsys.readouterr().out
    stage = Usd.Stage.Open(str(out))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0  # SI constants: the lengths are metres
    assert stage.GetStartTimeCode() == 0 and stage.GetEndTimeCode() == 6
    tets = [p for p in stage.Traverse() if p.IsA(UsdGeom.TetMesh)]
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)]
    assert len(tets) == 1 and len(meshes) == 1
    points = UsdGeom.PointBased(tets[0]).GetPointsAttr()
    assert len(points.GetTimeSamples()) == 7
    first, last = np.asarray(points.Get(0)), np.asarray(points.Get(6))
    assert first.shape == last.shape and last[:, 2].min() < first[:, 2].min() + 1e-6
    assert not np.array_equal(first, last)  # it moved under gravity
    surface = UsdGeom.PointBased(meshes[0]).GetPointsAttr()
    assert len(surface.GetTimeSamples()) == 7
