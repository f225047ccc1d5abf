"""Pictures of recorded stages (PNG frames, animated GIF) and ``warpblob view`` without a display."""

import imageio.v3 as iio
import numpy as np
import pytest

import warpblob as wb
import warpblob.usd
from warpblob.cli import main
from warpblob.cut import SweepSurface, cut
from warpblob.mesh import TetStructure, box_tetmesh


@pytest.fixture(scope="module")
def cut_stage(tmp_path_factory):
    """A box cut in two at frame 2 whose right piece then moves away along +x, with a probe on a path."""
    path = tmp_path_factory.mktemp("view") / "cut.usdc"
    s = TetStructure.from_tetmesh(box_tetmesh((0, 0, 0), (1, 1, 1), (3, 3, 3)))
    with wb.usd.Recorder(path, fps=10) as rec:
        rec.add(s, name="Box", model=wb.Point((0.5, 0.5, 0.5), 2.0, color=(0.8, 0.4, 0.3)))
        rec.add(wb.tools.Probe(0.1), wb.tools.Path.line((0.5, 0.5, 2.0), (0.5, 0.5, 1.2), 0.5))
        for frame in range(5):
            if frame == 2:
                cut(s, SweepSurface.plane((0.5, 0.5, 0.5), (1, 0, 0), 3.0))
            if frame > 2:
                x = np.asarray(s.node_rest).copy()
                labels = s.components()
                right = np.unique(np.asarray(s.cell_nodes)[labels == labels.max()])
                x[right, 0] += 0.2 * (frame - 2)
                s.set_positions(x)
            rec.frame()
    return path


def test_render_gif_writes_the_frames_and_an_animation(cut_stage, tmp_path):
    gif = wb.usd.render_gif(cut_stage, tmp_path / "cut.gif", window_size=(240, 180), progress=False)
    frames = sorted((tmp_path / "cut_frames").glob("cut_*.png"))
    assert [p.name for p in frames] == [f"cut_{k:05d}.png" for k in range(5)]
    movie = iio.imread(gif, index=None)
    assert movie.shape[0] == 5 and movie.shape[1:3] == (180, 240)
    first, last = iio.imread(frames[0]), iio.imread(frames[-1])
    # something is drawn (not a white picture), and the motion shows
    assert (first[..., :3] < 200).any(axis=-1).mean() > 0.02
    assert np.abs(first.astype(int) - last.astype(int)).max() > 50
    assert not list(tmp_path.glob(".*tmp*"))
    with pytest.raises(wb.SceneError, match=".gif"):
        wb.usd.render_gif(cut_stage, tmp_path / "cut.mp4")


def test_view_without_a_display_prints_how_to_open_the_stage(cut_stage, monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", str(cut_stage)]) == 0
    out = capsys.readouterr().out
    summary = wb.usd.stage_summary(cut_stage)
    assert f"usdview {cut_stage}" in out and "time codes 0..4" in out
    assert f"{summary['prims']} prims" in out and summary["tetmeshes"] == 1 and summary["animated"] > 0
    assert summary["start"] == 0 and summary["end"] == 4 and summary["default_prim"] == "/World"


def test_view_a_mesh_file_and_errors(tmp_path, capsys):
    stl = tmp_path / "ball.stl"
    wb.polygonize(wb.Point((0, 0, 0), 1.0), cellsize=0.3).to_pyvista().save(stl)
    assert main(["view", "--no-window", str(stl)]) == 0
    assert "points" in capsys.readouterr().out
    assert main(["view", str(tmp_path / "nothing.usda")]) == 1
    assert "no such file" in capsys.readouterr().err
    assert main(["view", str(tmp_path / "notes.txt")]) == 1
    assert "unknown file type" in capsys.readouterr().err
